"""Benchmarks: each module measures one part of the system and returns a results dict, writes it as
JSON and renders a markdown table; the CLI (``shgm-slam bench ...``) only prints them."""
