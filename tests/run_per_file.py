"""Run each test file in a pytest process of its own and sum the results (what `make test` runs).

Why: in one long pytest process the suite segfaulted while a test waited on a subprocess (2026-12-02,
3 of 3 full runs, at different tests once more files had run before); each file alone passes. Until
the cause is found (suspects: the native thread pools of OIDN, OpenVINO and Mitsuba in one process),
a process per file keeps one file's native state from another's. Extra pytest arguments pass through.
"""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

COUNTS = re.compile(r"(\d+) (passed|failed|skipped|errors?|xfailed|xpassed|deselected)")
NO_TESTS = 5  # pytest's exit status when a file has nothing selected (e.g. with -k)


def main(args: list[str]) -> int:
    totals: dict[str, int] = {}
    broken: list[str] = []
    for path in sorted(Path(__file__).parent.glob("test_*.py")):
        run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(path), *args],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        lines = run.stdout.rstrip().splitlines()
        print(f"{path.name}: {lines[-1] if lines else '(no output)'}", flush=True)
        if run.returncode not in (0, NO_TESTS):
            print(run.stdout, flush=True)
            broken.append(f"{path.name} (exit {run.returncode})")
        for number, kind in COUNTS.findall(lines[-1] if lines else ""):
            kind = "errors" if kind.startswith("error") else kind
            totals[kind] = totals.get(kind, 0) + int(number)
    if broken:
        print("failed files: " + ", ".join(broken))
    failed = totals.get("failed", 0) + totals.get("errors", 0)
    print(f"{totals.get('passed', 0)} passed, {failed} failed, {totals.get('skipped', 0)} skipped")
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
