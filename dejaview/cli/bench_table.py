"""A benchmark's table: the load average its header prints, its rows as CSV, its comma-separated
options parsed (shared by ``bench/*.py`` and ``dejaview bench``).
"""

from __future__ import annotations

import csv
import importlib.util
import sys
from pathlib import Path

import click


def load_average() -> str:
    """``load average 1 5 15 (N CPUs)`` for benchmark headers (machines are shared: say how busy)."""
    import os

    try:
        one, five, fifteen = os.getloadavg()
    except OSError:
        return "load average unknown"
    return f"load average {one:.2f} {five:.2f} {fifteen:.2f} ({os.cpu_count()} CPUs)"


def write_rows_csv(rows: list[dict], path) -> Path:
    """Write benchmark rows as CSV: one column per key (first-seen order), blank where absent."""
    fields: dict[str, None] = {}
    for row in rows:
        fields.update(dict.fromkeys(row))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(fields) or ["name"], restval="", lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    return path


def parse_names(text: str, choices) -> tuple[str, ...]:
    """``"gd, adam"`` -> ("gd", "adam"), each one of ``choices``.

    Raises:
        ValueError: empty, or a name not in ``choices``.
    """
    items = tuple(v for v in text.replace(" ", "").split(",") if v)
    bad = [v for v in items if v not in choices]
    if not items or bad:
        raise ValueError(f"expected a comma-separated list of {', '.join(choices)}, got {text!r}")
    return items


def parse_counts(text: str) -> tuple[int, ...]:
    """``"100,500,1000"`` -> (100, 500, 1000).

    Raises:
        ValueError: empty, not integers, or not positive.
    """
    try:
        counts = tuple(int(v) for v in text.replace(" ", "").split(",") if v)
    except ValueError:
        counts = ()
    if not counts or min(counts) < 1:
        raise ValueError(f"expected comma-separated positive integers (e.g. 100,500,1000), got {text!r}")
    return counts


def bench_module(name: str):
    """The module ``bench/<name>.py`` of the checkout this package lives in.

    Raises:
        click.ClickException: no such file (DejaView not installed from a checkout).
    """
    import dejaview

    root = Path(dejaview.__file__).resolve().parent.parent
    path = root / "bench" / f"{name}.py"
    if not path.is_file():
        raise click.ClickException(f"{path} not found: the benchmarks run from a source checkout "
                                   f"(pip install -e .)")
    key = f"dejaview_bench_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[key] = module
        try:
            spec.loader.exec_module(module)
        except BaseException:
            del sys.modules[key]
            raise
    return sys.modules[key]


def _comma_list(choices):
    def convert(ctx, param, value):
        try:
            return parse_names(value, choices)
        except ValueError as exc:
            raise click.BadParameter(str(exc)) from None
    return convert


csv_option = click.option("--csv", "csv_path", type=click.Path(dir_okay=False, path_type=Path),
                          help="Also write the rows as CSV to this file.")
check_option = click.option("--check", is_flag=True,
                            help="Exit with status 1 when a target is missed.")


def _finish(rows, csv_path, check, verdicts):
    if csv_path is not None:
        write_rows_csv(rows, csv_path)
        click.echo(f"wrote {csv_path}")
    if check and not all(verdicts):
        click.get_current_context().exit(1)
