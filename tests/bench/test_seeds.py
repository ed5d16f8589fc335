"""``--seeds`` of every benchmark: names, ranges and lists; repeats and negatives refused."""

from __future__ import annotations

import pytest

from shgm_slam.bench.seeds import parse_seeds
from shgm_slam.errors import ConfigError


def test_names_ranges_and_lists() -> None:
    assert parse_seeds("report", {"report": (210, 211)}) == (210, 211)
    assert parse_seeds("3-5") == (3, 4, 5)
    assert parse_seeds("7,9,8") == (7, 9, 8)
    assert parse_seeds("0") == (0,)


@pytest.mark.parametrize(
    ("text", "culprit"),
    [
        ("10,10", "seed 10 more than once"),  # counted twice before
        ("3,4,3", "seed 3 more than once"),
        ("5-3", "selects no world"),
        ("-1", "write"),
        ("a-b", "write"),
        ("1-2-3", "write"),
        ("1,,2", "write"),
        ("", "write"),
        ("report", "write A-B"),  # a name only where the benchmark has it
        ("2147483648", "0-2147483647"),
    ],
)
def test_what_would_mislead_is_refused(text: str, culprit: str) -> None:
    with pytest.raises(ConfigError, match=culprit):
        parse_seeds(text)
