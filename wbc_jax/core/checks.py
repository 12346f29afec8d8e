"""What a check script (experiments/checks/, benchmarks/benchmark.py, experiments/acceptance/cpu_targets.py) does
with its own output: a pure function ``failures(result) -> list[str]`` states its bar; the verdict goes into the
result file; the process exits with status 1 when any failure is found.

    result["check"] = checks.verdict(failures(result), BAR)
    ...write the result...
    sys.exit(checks.exit_status(result))
"""

from __future__ import annotations

import sys


def verdict(failures: list[str], bar: str) -> dict:
    """The ``check`` entry of a result: whether it passed, the bar in words, one line per failure."""
    return {"passed": not failures, "bar": bar, "failures": list(failures)}


def exit_status(result: dict) -> int:
    """0 when ``result["check"]`` passed; else each failure on stderr and 1. A result without a
    verdict is a failure (a check that did not run cannot pass)."""
    check = result.get("check") or {"passed": False, "failures": ["the result holds no check verdict"]}
    for line in check["failures"]:
        print(f"check failed: {line}", file=sys.stderr)
    return 0 if check["passed"] else 1
