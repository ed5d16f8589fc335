"""Where every benchmark writes its results: ``<stem>.json`` and ``<stem>.md``, each naming what computed it."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from shgm_slam.environment import environment, environment_line
from shgm_slam.io.json_text import to_json_text


def write_report(
    out: Path, stem: str, results: dict, markdown: Callable[[dict], str], *, indent: int | None = 1,
    name_environment: bool = True,
) -> tuple[Path, Path]:
    """``out/<stem>.json`` (the results, strict JSON: numpy scalars as floats, NaN as null, with the
    ``environment`` that computed them added to ``results``) and ``out/<stem>.md`` (``markdown(results)``, and with
    ``name_environment`` a line naming that environment; without it the file is the markdown alone, for tables
    pasted as they are); ``out`` is created. Returns both paths; ``indent`` as ``to_json_text``'s."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results.setdefault("environment", environment())
    js, md = out / f"{stem}.json", out / f"{stem}.md"
    js.write_text(to_json_text(results, indent=indent) + "\n")
    text = markdown(results)
    if name_environment:
        text = text.rstrip("\n") + "\n\n" + environment_line(results["environment"]) + "\n"
    md.write_text(text)
    return js, md
