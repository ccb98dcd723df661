"""Run a benchmark suite: btf bench SUITE [OPTIONS].

A plugin of the ``btf`` command (entry point group ``btf.commands`` in pyproject.toml), so that
``btf`` itself never imports the benchmarks: suites are imported only when ``btf bench`` runs.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from benchmarks.harness import to_json

SUITES = ("generate", "compress", "quilt", "roller", "enlarge", "tradeoff", "resume", "scene",
          "objectstore", "formats", "view", "checksums", "faults", "scaling", "precision",
          "mitsuba", "rendered", "writes")


class _Formatter(argparse.RawDescriptionHelpFormatter):
    def __init__(self, prog):
        super().__init__(prog, max_help_position=32)


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``btf bench``, one subcommand per suite."""
    parser = argparse.ArgumentParser(
        prog="btf bench", formatter_class=_Formatter,
        description="Benchmark a stage against a reference measured in the same run, and print "
                    "a Markdown table for BENCHMARKS.md (and JSON with --json FILE).")
    inner = parser.add_subparsers(dest="suite", metavar="SUITE", required=True)
    for name in SUITES:
        suite = importlib.import_module(f"benchmarks.{name}")
        p = inner.add_parser(name, help=(suite.__doc__ or "").splitlines()[0],
                             description=suite.__doc__, formatter_class=_Formatter)
        suite.add_arguments(p)
        p.add_argument("--json", metavar="FILE", help="also write the raw figures as JSON")
        p.set_defaults(suite_module=suite)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the suite named in ``argv``; returns the exit status."""
    args = build_parser().parse_args(sys.argv[2:] if argv is None else argv)
    suite = args.suite_module
    result = suite.run(args)
    if args.json:
        Path(args.json).write_text(to_json(result) + "\n")
    print(suite.report(result))
    rates = suite.rates(result) if hasattr(suite, "rates") else {}
    if rates:  # what btf run --plan estimates times from
        from pipeline.planning import record_rates

        print(f"rates for btf run --plan stored in {record_rates(rates, suite.SUITE)}",
              file=sys.stderr)
    return 0
