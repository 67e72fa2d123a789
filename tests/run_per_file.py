"""Run each test file in a pytest process of its own, JOBS files at a time, and sum the results (what
`make test` runs).

Why a process per file: in one long pytest process the suite segfaulted while a test waited on a
subprocess (2026-12-02, 3 of 3 full runs, at different tests once more files had run before); each file
alone passes. Until the cause is found (suspects: the native thread pools of OIDN, OpenVINO and Mitsuba
in one process), a process per file keeps one file's native state from another's.

Why several at once: the tests run torch on one thread (conftest.one_torch_thread) and spend much of
their time importing torch, Mitsuba and OpenVINO in CLI subprocesses, which is one core's work, so one
file at a time leaves a core idle. `--jobs` (default: the CPU count, at most 2, which is what the suite
is sized for) sets how many files run at once; `--jobs 1` runs them in turn. Extra pytest arguments
pass through.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

COUNTS = re.compile(r"(\d+) (passed|failed|skipped|errors?|xfailed|xpassed|deselected)")
NO_TESTS = 5  # pytest's exit status when a file has nothing selected (e.g. with -k)
MAX_DEFAULT_JOBS = 2


def run_file(path: Path, args: list[str]) -> tuple[Path, int, str]:
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(path), *args],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    return path, run.returncode, run.stdout


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("--jobs", "-j", type=int, default=min(os.cpu_count() or 1, MAX_DEFAULT_JOBS),
                        help="test files run at once (default: the CPU count, at most 2)")
    options, args = parser.parse_known_args(argv)
    if options.jobs < 1:
        parser.error(f"--jobs must be at least 1, got {options.jobs}")
    files = sorted(Path(__file__).parent.glob("test_*.py"))
    totals: dict[str, int] = {}
    broken: list[str] = []
    start = time.monotonic()
    with ThreadPoolExecutor(options.jobs) as pool:
        for path, returncode, stdout in pool.map(lambda p: run_file(p, args), files):
            lines = stdout.rstrip().splitlines()
            print(f"{path.name}: {lines[-1] if lines else '(no output)'}", flush=True)
            if returncode not in (0, NO_TESTS):
                print(stdout, flush=True)
                broken.append(f"{path.name} (exit {returncode})")
            for number, kind in COUNTS.findall(lines[-1] if lines else ""):
                kind = "errors" if kind.startswith("error") else kind
                totals[kind] = totals.get(kind, 0) + int(number)
    if broken:
        print("failed files: " + ", ".join(broken))
    failed = totals.get("failed", 0) + totals.get("errors", 0)
    print(f"{totals.get('passed', 0)} passed, {failed} failed, {totals.get('skipped', 0)} skipped "
          f"({len(files)} files, {options.jobs} at a time, {(time.monotonic() - start) / 60:.1f} min)")
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
