"""How long a ``voxe`` service command takes to start and answer, before and after a change, interleaved in one run.

``voxe status J`` had imported torch (and the library's dataset and tensor-file modules) before every command, so a
command that only asks the service a question took seconds. Each case runs ``python -m voxe_core.cli ...`` as its own
process against two copies of the code: ``--before REV`` (``voxe_core`` and ``voxe_client`` exported from git) and this
working tree, alternating which goes first each round:

* ``status --help``: parsing only, which imported no torch before either (the control);
* ``status J``, the service answering (a stub on loopback serving one job's JSON);
* ``status J``, the service refused (a port nothing listens on): the error path, exit 3.

Beside the wall times (medians and their ratio, after / before), what was kept equal: each case's exit status,
stdout and stderr must be the same in both copies (the run stops otherwise), and one ``-X importtime`` run per copy
says whether torch was imported and how many modules were.

    python bench/cli_startup.py --before 34340db    # ~2 min on 2 cores (the torch-loading copy takes seconds a run)

Writes bench/results/cli_startup.json and .png; prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from io import BytesIO
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path[:0] = [str(REPO), str(HERE), str(REPO / "tests")]
from reconstruction import commit_measured  # noqa: E402
from service_helpers import free_port  # noqa: E402

JOB = {"id": "j1", "state": "running", "stage": "edit", "overall_progress": 0.25}


class _Service(BaseHTTPRequestHandler):
    """Answers every GET with :data:`JOB` (what ``voxe status j1`` asks for)."""

    def do_GET(self):
        body = json.dumps(JOB).encode()
        self.send_response(200)
        self.send_header("content-type", "application/json")
        self.send_header("content-length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


def export_tree(rev: str, into: Path) -> Path:
    """``voxe_core`` and ``voxe_client`` as they are at ``rev``, written under ``into``."""
    archive = subprocess.run(["git", "archive", "--format=tar", rev, "voxe_core", "voxe_client"], cwd=REPO,
                             capture_output=True, check=True).stdout
    with tarfile.open(fileobj=BytesIO(archive)) as tar:
        tar.extractall(into, filter="data")
    return into


def run_voxe(tree: Path, argv: list[str], importtime: bool = False) -> dict:
    """``voxe ARGV`` run from the code in ``tree``: wall seconds, exit status, stdout, stderr; with ``importtime``
    also the modules it imported (and stderr without their lines)."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    command = [sys.executable, *(["-X", "importtime"] if importtime else []), "-m", "voxe_core.cli", *argv]
    start = time.perf_counter()
    result = subprocess.run(command, env=env, cwd=tempfile.gettempdir(), capture_output=True, text=True, timeout=120)
    seconds = time.perf_counter() - start
    lines = result.stderr.splitlines(keepends=True)
    said = {"seconds": seconds, "status": result.returncode, "stdout": result.stdout,
            "stderr": "".join(line for line in lines if not line.startswith("import time:"))}
    if importtime:
        said["modules"] = {line.rsplit("|", 1)[1].strip() for line in lines if line.startswith("import time:")}
    return said


def measure(trees: dict[str, Path], cases: dict[str, list[str]], rounds: int) -> list[dict]:
    rows = []
    for case, argv in cases.items():
        runs = {arm: [] for arm in trees}
        for round_ in range(rounds + 1):  # round 0 warms the page cache, not kept
            for arm in (list(trees) if round_ % 2 else list(trees)[::-1]):
                said = run_voxe(trees[arm], argv)
                if round_:
                    runs[arm].append(said)
        first = {arm: runs[arm][0] for arm in trees}
        outputs = {arm: (said["status"], said["stdout"], said["stderr"]) for arm, said in first.items()}
        if len(set(outputs.values())) != 1 or any((s["status"], s["stdout"], s["stderr"]) != outputs[arm]
                                                   for arm in trees for s in runs[arm]):
            raise SystemExit(f"{case}: the two copies answered differently: {outputs}")
        imports = {arm: run_voxe(trees[arm], argv, importtime=True)["modules"] for arm in trees}
        median = {arm: statistics.median(s["seconds"] for s in runs[arm]) for arm in trees}
        rows.append({
            "case": case, "argv": argv, "status": outputs["after"][0], "same_output": True,
            "stderr": outputs["after"][2],
            **{f"{arm}_seconds": [round(s["seconds"], 4) for s in runs[arm]] for arm in trees},
            **{f"{arm}_median_s": round(median[arm], 4) for arm in trees},
            "ratio_after_to_before": round(median["after"] / median["before"], 3),
            **{f"{arm}_imports_torch": "torch" in imports[arm] for arm in trees},
            **{f"{arm}_modules": len(imports[arm]) for arm in trees},
        })
    return rows


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    for i, row in enumerate(rows):
        for j, arm in enumerate(("before", "after")):
            x = i + (j - 0.5) * 0.35
            ax.bar(x, row[f"{arm}_median_s"], 0.35, color=f"C{j}", label=arm if i == 0 else None)
            ax.plot([x] * len(row[f"{arm}_seconds"]), row[f"{arm}_seconds"], "k.", markersize=3)
        ax.annotate(f"×{row['ratio_after_to_before']:.2f}", (i + 0.175, row["after_median_s"]), ha="center",
                    va="bottom", fontsize=8)
    ax.set_xticks(range(len(rows)), [f"{row['case']}\n(exit {row['status']})" for row in rows], fontsize=8)
    ax.set_ylabel("wall seconds per process (bars: median, dots: rounds)")
    ax.set_title("voxe service commands: start-up to exit, before and after (labels: after / before)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--before", required=True, metavar="REV", help="the code to compare this working tree with")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--out", type=Path, default=HERE / "results" / "cli_startup.json")
    args = parser.parse_args(argv)
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as scratch, ThreadingHTTPServer(("127.0.0.1", 0), _Service) as server:
        threading.Thread(target=server.serve_forever, daemon=True).start()
        trees = {"before": export_tree(args.before, Path(scratch)), "after": REPO}
        cases = {"status --help": ["status", "--help"],
                 "status, service answering": ["status", "j1", "--api", f"http://127.0.0.1:{server.server_port}"],
                 "status, service refused": ["status", "j1", "--api", f"http://127.0.0.1:{free_port()}"]}
        rows = measure(trees, cases, args.rounds)
        server.shutdown()
    before = subprocess.run(["git", "rev-parse", "--short", args.before], cwd=REPO, capture_output=True,
                            text=True).stdout.strip()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "what": "voxe service commands as processes, before and after, interleaved; see bench/cli_startup.py",
        "before": before, "after": commit_measured(), "rounds": args.rounds, "python": sys.version.split()[0],
        "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)], "rows": rows,
    }, indent=2) + "\n")
    plot(rows, args.out.with_suffix(".png"))
    for row in rows:
        print(f"{row['case']:28s} exit {row['status']}  before {row['before_median_s']:.3f} s (torch "
              f"{'yes' if row['before_imports_torch'] else 'no'}, {row['before_modules']} modules)  after "
              f"{row['after_median_s']:.3f} s (torch {'yes' if row['after_imports_torch'] else 'no'}, "
              f"{row['after_modules']} modules)  after / before x{row['ratio_after_to_before']:.2f}  same output")
    return 0


if __name__ == "__main__":
    sys.exit(main())
