"""Run every benchmark script in this folder, one after the other, and write RESULTS.md.

A benchmark is a ``benchmarks/*.py`` script with an ``if __name__ == "__main__":`` block; each
prints its figures against a baseline measured in the same run. Each runs in its own process
(group) with its default arguments, stopped after its ``BUDGET_SECONDS`` (a top-level constant
in the script, read without importing it; 180 s when absent) and within a total deadline of
``--deadline`` seconds (900 by default: the whole run stays under 15 minutes; the bag layouts of
bag_conversion.py take up to 420 s of it). Scripts run
sequentially, never side by side: they measure time on a small machine. A script with a top-level
``OPT_IN = True`` (the 30-minute soak) runs only when named.

    .venv/bin/python -m benchmarks                 # all of them; rewrites benchmarks/RESULTS.md
    .venv/bin/python -m benchmarks startup walls_4000 --results /tmp/r.md   # a selection
    .venv/bin/python -m benchmarks --list

RESULTS.md is rewritten above the notes marker; the hand-written notes below it (profiles of the
missed targets) are kept.
"""

from __future__ import annotations

import argparse
import ast
import datetime
import os
import platform
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "RESULTS.md"
NOTES_MARKER = "<!-- Everything below this line is written by hand and kept by python -m benchmarks. -->"
DEFAULT_BUDGET_S = 180.0
DEADLINE_S = 900.0
VERSIONS = ("rerun-sdk", "eclipse-zenoh", "rosbags", "numpy", "opencv-python-headless")
STDERR_TAIL = 1500  # characters of a failed script's stderr kept in the results


@dataclass(frozen=True, slots=True)
class Benchmark:
    path: Path
    budget_s: float
    opt_in: bool = False
    """Run only when named (a top-level ``OPT_IN = True``: longer than a whole run may take)."""

    @property
    def name(self) -> str:
        return self.path.stem


@dataclass(frozen=True, slots=True)
class Outcome:
    benchmark: Benchmark
    seconds: float
    status: str  # "ok", "exit N", "stopped after N s", "not run: ..."
    stdout: str
    stderr_tail: str


def is_main_guard(node: ast.stmt) -> bool:
    return (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
            and isinstance(node.test.left, ast.Name) and node.test.left.id == "__name__")


def budget(tree: ast.Module) -> float:
    for node in tree.body:
        if (isinstance(node, ast.Assign) and len(node.targets) == 1
                and isinstance(node.targets[0], ast.Name) and node.targets[0].id == "BUDGET_SECONDS"
                and isinstance(node.value, ast.Constant)
                and isinstance(node.value.value, int | float)):
            return float(node.value.value)
    return DEFAULT_BUDGET_S


def opt_in(tree: ast.Module) -> bool:
    return any(
        isinstance(node, ast.Assign) and len(node.targets) == 1
        and isinstance(node.targets[0], ast.Name) and node.targets[0].id == "OPT_IN"
        and isinstance(node.value, ast.Constant) and node.value.value is True
        for node in tree.body
    )


def discover() -> list[Benchmark]:
    found = []
    for path in sorted(HERE.glob("*.py")):
        if path.name.startswith("_"):
            continue
        tree = ast.parse(path.read_text(), filename=str(path))
        if any(is_main_guard(node) for node in tree.body):
            found.append(Benchmark(path, budget(tree), opt_in(tree)))
    return found


def stop_group(proc: subprocess.Popen[str]) -> None:
    """End the script and whatever it started (its own process group), politely first."""
    for sig, grace in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=grace)
            return
        except subprocess.TimeoutExpired:
            continue


def run(benchmark: Benchmark, timeout_s: float) -> Outcome:
    """Runs the script, echoing its output as it comes, for at most ``timeout_s``."""
    print(f"== {benchmark.name} (at most {timeout_s:.0f} s)", flush=True)
    lines: list[str] = []
    with tempfile.TemporaryFile("w+") as stderr:
        started = time.perf_counter()
        proc = subprocess.Popen([sys.executable, str(benchmark.path)], cwd=ROOT, text=True,
                                stdout=subprocess.PIPE, stderr=stderr, start_new_session=True)
        output = proc.stdout
        assert output is not None

        def echo() -> None:
            for line in output:
                lines.append(line)
                print(line, end="", flush=True)

        reader = threading.Thread(target=echo, daemon=True)
        reader.start()
        try:
            code = proc.wait(timeout=timeout_s)
            status = "ok" if code == 0 else f"exit {code}"
        except subprocess.TimeoutExpired:
            stop_group(proc)
            status = f"stopped after {timeout_s:.0f} s"
        reader.join(timeout=5.0)
        seconds = time.perf_counter() - started
        stderr.seek(0)
        tail = "" if status == "ok" else stderr.read()[-STDERR_TAIL:]
    return Outcome(benchmark, seconds, status, "".join(lines), tail)


def command_output(*command: str) -> str:
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, check=False)
    return done.stdout.strip()


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def version(distribution: str) -> str:
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return "not installed"


def load_average() -> str:
    return " ".join(f"{value:.2f}" for value in os.getloadavg())


def machine_lines() -> list[str]:
    dirty = " with uncommitted changes" if command_output("git", "status", "--porcelain") else ""
    return [
        f"- date: {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC",
        f"- machine: {cpu_model()}, {os.cpu_count()} cores, {platform.system()} "
        f"{platform.release()}; load average (1, 5, 15 min) when the run began {load_average()} "
        "(the machine is shared: other work slows every figure, baselines included)",
        f"- python {platform.python_version()}; "
        + ", ".join(f"{name} {version(name)}" for name in VERSIONS),
        f"- tree: {command_output('git', 'rev-parse', '--short', 'HEAD')}{dirty}",
    ]


def kept_notes(results: Path) -> str:
    if not results.exists():
        return f"{NOTES_MARKER}\n\n## Notes\n"
    text = results.read_text()
    at = text.find(NOTES_MARKER)
    return text[at:] if at >= 0 else f"{NOTES_MARKER}\n\n## Notes\n"


def write_results(results: Path, header: list[str], outcomes: list[Outcome], total_s: float) -> None:
    parts = [
        "# Benchmark results",
        "",
        "The last run of `.venv/bin/python -m benchmarks` (written by it). Every figure is set "
        "against a baseline measured in the same run; each script's docstring says what it "
        "measures and how.",
        "",
        *header,
        f"- total: {total_s:.0f} s for {len(outcomes)} benchmark(s); load average at the end "
        f"{load_average()}",
        "",
    ]
    for outcome in outcomes:
        parts += [f"## {outcome.benchmark.name} ({outcome.seconds:.0f} s, {outcome.status})", "",
                  "```", outcome.stdout.rstrip() or "(no output)", "```", ""]
        if outcome.stderr_tail:
            parts += ["stderr (end):", "", "```", outcome.stderr_tail.rstrip(), "```", ""]
    results.write_text("\n".join(parts) + "\n" + kept_notes(results))


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help="run only these benchmarks (file names without .py)")
    parser.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    parser.add_argument("--deadline", type=float, default=DEADLINE_S,
                        help="seconds for the whole run (default %(default)s)")
    parser.add_argument("--results", type=Path, default=None,
                        help="write the results here (default: benchmarks/RESULTS.md for a full run, "
                             "nowhere for a selection)")
    args = parser.parse_args()
    # Started in the background (``python -m benchmarks &``), the run would pass SIGINT on
    # ignored, and live_capacity's viewer never finished its file (2026-11-29, 23:43).
    from tests.integration.procs import stop_signals_back

    stop_signals_back()
    benchmarks = discover()
    if args.list:
        for benchmark in benchmarks:
            note = " (opt-in: run it by name)" if benchmark.opt_in else ""
            print(f"{benchmark.name:<20} at most {benchmark.budget_s:.0f} s{note}")
        return 0
    unknown = sorted(set(args.names) - {b.name for b in benchmarks})
    if unknown:
        parser.error(f"no benchmark named {', '.join(unknown)}; "
                     f"there are {', '.join(b.name for b in benchmarks)}")
    selected = [b for b in benchmarks if b.name in args.names or not (args.names or b.opt_in)]
    results = args.results if args.results is not None or args.names else RESULTS
    header = machine_lines()
    print("\n".join(header), flush=True)
    started = time.perf_counter()
    outcomes = []
    for benchmark in selected:
        remaining = args.deadline - (time.perf_counter() - started)
        if remaining < 10.0:
            outcomes.append(Outcome(benchmark, 0.0, "not run: the run's deadline was spent", "", ""))
            continue
        outcomes.append(run(benchmark, min(benchmark.budget_s, remaining)))
    total = time.perf_counter() - started
    print(f"== {len(outcomes)} benchmark(s) in {total:.0f} s: "
          + ", ".join(f"{o.benchmark.name} {o.status}" for o in outcomes), flush=True)
    if results is not None:
        write_results(results, header, outcomes, total)
        print(f"wrote {results}")
    return 0 if all(o.status == "ok" for o in outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
