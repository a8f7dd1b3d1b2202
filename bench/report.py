"""One speed-against-error report for the whole pipeline: bench/REPORT.md (issue 7).

Runs the stage benchmarks (reconstruction, segmentation, edit step, service
load), or only reads what they last wrote, and writes a Markdown report in
which every speed figure stands beside the accuracy it bought in the same run,
with one plot per stage and the trade-offs a user chooses between (grid
resolution, samples per ray, empty-space skipping, iteration budgets, fp16 vs
fp32). Where a figure was never measured the report says so.

    python bench/report.py --collect-only   # read bench/results/*.json -> bench/REPORT.md (seconds)
    python bench/report.py --quick          # CI sizes; everything under bench/results/quick/ (~15 min on 2 cores)
    python bench/report.py --full           # full sizes (hours on 2 cores), then bench/REPORT.md

``--quick`` never overwrites the full-size record in bench/results/: its JSON,
plots and report go to bench/results/quick/. A stage whose script is missing
or fails is reported as such; the others still are.
"""

from __future__ import annotations

import argparse
import datetime as dt
import itertools
import json
import math
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
QUICK_RESULTS = RESULTS / "quick"
REPORT = HERE / "REPORT.md"


@dataclass(frozen=True)
class Stage:
    name: str
    title: str
    script: str
    quick_args: tuple[str, ...]
    result: str  # JSON file name the script writes (each script takes --out)


STAGES = (
    Stage("reconstruction", "Reconstruction (SPEC §1)", "reconstruction.py", ("--quick",), "reconstruction.json"),
    Stage("segmentation", "Spatial refinement: lifting + graph cut (SPEC §3)", "segmentation.py", ("--quick",),
          "segmentation.json"),
    Stage("edit_step", "Editing step: SDS + L_reg3D (SPEC §2)", "edit_step.py", ("--quick",), "edit_step.json"),
    Stage("service_load", "Job service under load", "service_load.py",
          ("--pollers", "10", "--jobs", "100", "--seconds", "5"), "service_load.json"),
)


# ------------------------------------------------------------------ running


def run_stage(stage: Stage, quick: bool, results: Path, timeout_s: float | None) -> str | None:
    """Run one benchmark so that its JSON lands in ``results``; a note when it could not run, else None."""
    script = HERE / stage.script
    if not script.is_file():
        return f"`bench/{stage.script}` does not exist (yet), so this stage was not measured."
    args = [sys.executable, str(script), *(stage.quick_args if quick else ()), "--out", str(results / stage.result)]
    print(f"[report] {' '.join(args[1:])}", flush=True)
    try:
        done = subprocess.run(args, cwd=HERE.parent, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return f"`bench/{stage.script}` ran past {timeout_s:.0f} s and was stopped; no fresh results."
    if done.returncode != 0:
        tail = " ".join((done.stderr or done.stdout).strip().splitlines()[-3:])[-400:]
        return f"`bench/{stage.script}` failed (exit {done.returncode}): {tail}"
    return None


def write_results(stem: str, runs: list[dict], summary: dict, plot) -> None:
    """A benchmark's ``{"runs", "summary"}`` as results/<stem>.json, ``plot(runs, path)`` as its PNG, the summary
    printed: what a script measuring runs into one summary writes."""
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps({"runs": runs, "summary": summary}, indent=1) + "\n")
    plot(runs, RESULTS / f"{stem}.png")
    print(json.dumps(summary, indent=1))


def load_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def as_runs(data) -> list[dict]:
    """Benchmarks write either a list of runs or a dict holding them under "runs" (or "rows")."""
    if isinstance(data, dict):
        data = data.get("runs", data.get("rows", []))
    return [r for r in data or [] if isinstance(r, dict)]


# ------------------------------------------------------------------ formatting


def fmt(value, digits: int = 2) -> str:
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def significant(value: float, digits: int = 3) -> str:
    """``value`` to ``digits`` significant digits in plain notation: a column of times from hundredths of a second to
    tens (a fixed number of decimals showed 0.047 s as 0.0).

    Examples:
        >>> significant(0.0468), significant(12.677), significant(0.0)
        ('0.0468', '12.7', '0')
    """
    if not value:
        return "0"
    return f"{value:.{max(0, digits - 1 - math.floor(math.log10(abs(value))))}f}"


def table(header: list[str], rows: list[list]) -> list[str]:
    r"""A Markdown table, each cell's text on one line with its pipes escaped (a command's stderr, newline and all,
    had broken its row in two).

    Examples:
        >>> table(["case", "stderr"], [["refused", "error: no | service\n"]])[2]
        '| refused | error: no \\| service |'
    """
    def cell(value) -> str:
        return " ".join((value if isinstance(value, str) else fmt(value)).split()).replace("|", r"\|")

    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + [
        "| " + " | ".join(cell(c) for c in row) + " |" for row in rows]


def ratio(a, b) -> str:
    return f"{a / b:.2f}×" if a and b else "–"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def relative(path: Path, report: Path) -> str:
    try:
        return str(path.relative_to(report.parent))
    except ValueError:
        return str(path)


def figure_link(fig, path: Path, report: Path, alt: str,
                layout: tuple[float, float, float, float] = (0, 0, 1, 1)) -> list[str]:
    """Save ``fig`` to ``path`` and return the Markdown lines that show it in ``report``; ``layout``: the part of
    the figure its axes are fitted in (what :func:`speed_error_axes` returns)."""
    import matplotlib.pyplot as plt

    fig.tight_layout(rect=layout)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return ["", f"![{alt}]({relative(path, report)})"]


# ------------------------------------------------------------------ speed-against-error plots

# The authors' code on mic (SPEC: 30.61 dB after 1,591 s of training on this CPU class) and the paper's edit
# (~50 min for 8,000 iterations on an RTX A5000): what every measured figure is read against.
AUTHORS_MIC = (1591.0, 30.61)
PAPER_EDIT_MINUTES = 50.0
DEVICE_STYLE = {"cpu": ("o", "#4c72b0", "CPU run"), "cuda": ("^", "#dd8452", "GPU run")}


def device_kind(run: dict) -> str:
    """``"cuda"`` for a GPU run (any ``cuda:N``), else ``"cpu"`` (older results carry no ``device``)."""
    return "cuda" if str(run.get("device") or "cpu").startswith("cuda") else "cpu"


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats (lower x and higher y), in order of increasing x.

    Examples:
        >>> pareto_front([(1, 1), (2, 3), (3, 2), (4, 4)])
        [0, 1, 3]
    """
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], float("-inf")
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def pareto_fronts(runs: list[dict], x: str, y: str) -> dict[str, list[dict]]:
    """Per device kind (:func:`device_kind`), its runs no other run of that device beats (lower ``x``, higher
    ``y``), in order of increasing ``x``: a CPU's seconds and a GPU's do not compare, so each device has its own
    front. A run marked ``stale`` (its recipe has changed since it ran) is on none.

    Examples:
        >>> cpu, gpu = {"s": 10, "db": 30}, {"s": 2, "db": 31, "device": "cuda"}
        >>> pareto_fronts([cpu, gpu, {**gpu, "s": 1, "stale": True}], "s", "db") == {"cpu": [cpu], "cuda": [gpu]}
        True
    """
    fronts = {}
    for kind in DEVICE_STYLE:
        mine = [r for r in runs if device_kind(r) == kind and not r.get("stale")]
        fronts[kind] = [mine[i] for i in pareto_front([(r[x], r[y]) for r in mine])]
    return fronts


def place_labels(anchors: list[tuple[float, float]], widths: list[float], height: float) -> list[float]:
    """A y per label (display units) so that no two label boxes overlap.

    Label ``i`` spans ``[x_i, x_i + widths[i]]`` horizontally and ``height`` vertically; lowest points first,
    each takes the free slot nearest its point, one label height at a time, above before below, so a crowd
    spreads both ways around its points instead of climbing off the axes.

    Examples:
        >>> place_labels([(0, 0), (0, 0), (0, 0), (100, 0)], [50, 50, 50, 50], 10)
        [0, 10, -10, 0]
    """
    placed: list[tuple[float, float, float]] = []  # (x0, x1, y)
    ys = [0.0] * len(anchors)
    for i in sorted(range(len(anchors)), key=lambda i: anchors[i][1]):
        x0, y0 = anchors[i]
        x1 = x0 + widths[i]
        for k in itertools.count():  # offsets 0, +1, -1, +2, -2, ... heights
            y = y0 + height * ((k + 1) // 2) * (1 if k % 2 else -1)
            # rounding: a label exactly one height away does not overlap
            if not any(a0 < x1 and x0 < a1 and abs(y - ay) < height * (1 - 1e-9) for a0, a1, ay in placed):
                break
        placed.append((x0, x1, y))
        ys[i] = y
    return ys


def speed_error_axes(ax, runs: list[dict], *, x: str, y: str, label, xlabel: str, ylabel: str, title: str,
                     hollow=lambda run: False, labels_beside: int = 10) -> tuple[float, float, float, float]:
    """Scatter ``runs`` as ``y`` against ``x`` (log axis), marker and colour by device, each device's Pareto front
    (lower ``x``, higher ``y``; :func:`pareto_fronts`) joined, each point labelled by ``label(run)`` without
    overlaps; draw anything else (anchors) on ``ax`` before, since the labels are placed last. A run with
    ``{y}_range`` (lowest, highest) gets a bar over it (:func:`seed_means`); a run marked ``stale`` is drawn faded.
    More than ``labels_beside`` points: each is numbered (left to right) and the labels are listed beside the axes,
    as a crowd of long labels would stack far from its points. Returns the part of the figure the axes were fitted
    in (for :func:`figure_link`)."""
    from matplotlib.colors import to_rgba
    from matplotlib.ticker import FuncFormatter

    points = [r for r in runs if r.get(x) is not None and r.get(y) is not None]
    ax.set_xscale("log")
    # Plain numbers at 1, 2 and 5 of each decade (the default minor labels of a short log axis run into each other).
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if f"{v:.0e}"[0] in "25" else ""))
    ranges = [r for r in points if r.get(f"{y}_range")]  # a run over seeds: its lowest to highest (``seed_means``)
    if ranges:
        ax.vlines([r[x] for r in ranges], *zip(*(r[f"{y}_range"] for r in ranges)), color=DEVICE_STYLE["cpu"][1],
                  linewidth=1, zorder=2)
    for kind, (marker, colour, name) in DEVICE_STYLE.items():
        for stale in (False, True):
            mine = [r for r in points if device_kind(r) == kind and bool(r.get("stale")) == stale]
            shade = to_rgba(colour, 0.4 if stale else 1)  # an alpha= argument would fill the hollow markers
            if mine:
                ax.scatter([r[x] for r in mine], [r[y] for r in mine], marker=marker, s=36, zorder=3, edgecolors=shade,
                           facecolors=[("none" if hollow(r) else shade) for r in mine],
                           label=f"{name}, stale: its recipe has changed since (rerun due)" if stale else name)
    for kind, front in pareto_fronts(points, x, y).items():
        if len(front) > 1:
            name = DEVICE_STYLE[kind][2]
            ax.step([r[x] for r in front], [r[y] for r in front], where="post", color=DEVICE_STYLE[kind][1],
                    linestyle="--", linewidth=1, zorder=2,
                    label=f"Pareto front, {name}s (no other {name} both faster and better)")
    ax.grid(True, which="both", color="0.92", linewidth=0.6)
    ax.margins(x=0.12, y=0.18)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=7, loc="lower right")
    if len(points) <= labels_beside:
        annotate_without_overlap(ax, [(r[x], r[y], label(r)) for r in points])
        return (0, 0, 1, 1)
    points.sort(key=lambda r: (r[x], r[y]))
    width, height = ax.figure.get_size_inches()
    ax.figure.set_size_inches(width + 3.5, height)  # room for the list
    # A figure text (the layout leaves it out of the axes' room) against the right edge; its room is measured at
    # the screen's dpi with a tenth to spare, as text widths do not scale exactly with the saved file's dpi.
    fig = ax.figure
    listed = fig.text(0.995, 0.93, "\n".join(f"{n:>2}  {label(r)}" for n, r in enumerate(points, 1)), va="top",
                      ha="right", multialignment="left", fontsize=6.5, family="monospace")
    fig.canvas.draw()
    room = 1 - (1.1 * listed.get_window_extent().width + 24) / fig.bbox.width
    annotate_without_overlap(ax, [(r[x], r[y], str(n)) for n, r in enumerate(points, 1)], layout=(0, 0, room, 1))
    return (0, 0, room, 1)


def annotate_without_overlap(ax, labelled: list[tuple[float, float, str]], fontsize: int = 7,
                             layout: tuple[float, float, float, float] = (0, 0, 1, 1)) -> None:
    """Write each label just right of its point, moved as :func:`place_labels` says, with a leader line;
    ``layout``: the figure's part (left, bottom, right, top) the tight layout fits the axes in.

    Placed twice: the labels change the tight layout, which moves the points on screen."""
    fig = ax.figure
    notes = [ax.annotate(text, (px, py), xytext=(px, py), fontsize=fontsize, va="center",
                         arrowprops={"arrowstyle": "-", "color": "0.6", "linewidth": 0.5}) for px, py, text in labelled]
    for _ in range(2):
        fig.tight_layout(rect=layout)
        fig.canvas.draw()
        to_display, to_data = ax.transData.transform, ax.transData.inverted().transform
        points = [tuple(to_display((px, py))) for px, py, _ in labelled]
        gap = 6.0  # display units between a point and its label
        boxes = [note.get_window_extent() for note in notes]
        height = max((b.height for b in boxes), default=0) * 1.15
        ys = place_labels([(px + gap, py) for px, py in points], [b.width for b in boxes], height)
        for note, (px, _), y in zip(notes, points, ys):
            note.xyann = tuple(to_data((px + gap, y)))

# ------------------------------------------------------------------ stages


def reconstruction_section(data, gpu, results: Path, report: Path) -> tuple[list[str], list[str]]:
    """(section lines, trade-off bullets) from reconstruction.json, with gpu.json's reconstruction runs plotted beside."""
    runs = as_runs(data)
    gpu_runs = [r for r in as_runs(gpu) if r.get("kind") == "reconstruction"]
    if not runs:
        return ["No runs in the file."], []
    lines = [
        "Each run trains in its own process on the shared CPU (`CPU s`: its CPU seconds, which say how much of the "
        "wall time was its own); test PSNR/SSIM are over the held-out views. "
        "`samples/ray` counts grid evaluations per test ray with skipping on (`dense`: the same trained grid "
        "rendered without skipping). `filter`: the images' antialiasing filter for training and ground truth; "
        "`other GT`: the same renders scored against the other filter's ground truth. `early stop`: whether the "
        "training renders ran the early-stop density pass (object fits did by default until 90eb259: the rows "
        "measured at earlier commits ran it, and `bench/reconstruction.py` reruns their labels with it); `commit`: "
        "the code measured. Rows measured at different commits compare as different runs.", "",
    ]
    lines += table(
        ["run", "scene", "grid", "iterations", "skipping", "filter", "early stop", "train s", "CPU s", "PSNR dB",
         "SSIM", "other GT PSNR / SSIM", "samples/ray (dense)", "render s/view (dense)", "peak RSS MB", "commit"],
        [[r.get("label", "–"), r.get("scene"), r.get("resolution"), r.get("iterations"), r.get("skipping"),
          r.get("resample", "box"), None if r.get("early_stop") is None else bool(r["early_stop"]), r.get("seconds"),
          r.get("cpu_seconds", "–"), r.get("psnr"), fmt(r.get("ssim"), 4), _other_ground_truth(r),
          f"{fmt(r.get('samples_per_ray'), 1)} ({fmt(r.get('dense_render_samples_per_ray'), 1)})",
          f"{fmt(r.get('render_seconds_per_view'), 3)} ({fmt(r.get('dense_render_render_seconds_per_view'), 3)})",
          fmt(r.get("peak_rss_mb"), 0), r.get("commit", "–")] for r in runs],
    )
    machines = sorted({r["machine"] for r in runs if r.get("machine")})
    if machines:
        lines += ["", f"Machine: {'; '.join(machines)}."]
    plot = results / "report_reconstruction.png"
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8.5, 5.2))
    stale = [run for _, run, _, _ in stale_gpu_runs(gpu_runs, runs)]
    plotted = seed_means(runs) + [{**r, "stale": True} if any(r is s for s in stale) else r for r in gpu_runs]
    ax.scatter(*AUTHORS_MIC, marker="*", s=160, color="black", zorder=4,
               label=f"authors' code, mic: {AUTHORS_MIC[1]} dB after {AUTHORS_MIC[0]:,.0f} s (CPU)")
    layout = speed_error_axes(ax, plotted, x="seconds", y="psnr", hollow=lambda r: r.get("skipping") is False,
                              label=_reconstruction_label, xlabel="training wall time (s, log scale)",
                              ylabel="mean test PSNR (dB)",
                              title="Reconstruction of mic: PSNR against training time (hollow: no empty-space skipping)")
    lines += figure_link(fig, plot, report, "PSNR vs seconds", layout)
    return lines, reconstruction_tradeoffs(runs)


SEED_SUFFIX = re.compile(r"-seed\d+(?=(-box)?$)")
"""A seed copy's part of a run label (``X-seed1``, ``X-seed1-box``): the recipe is the label without it."""


def seed_families(runs: list[dict]) -> dict[str, list[dict]]:
    """The labelled runs by recipe: each label without its seed part (``SEED_SUFFIX``), in first-seen order."""
    families: dict[str, list[dict]] = {}
    for r in runs:
        if r.get("label"):
            families.setdefault(SEED_SUFFIX.sub("", r["label"]), []).append(r)
    return families


def seed_means(runs: list[dict]) -> list[dict]:
    """``runs`` with each recipe run over seeds (``X``, ``X-seed1``, ...) as one run labelled ``X`` at its mean
    seconds and PSNR (each seed's seconds its own run's, so the mean is only a place on the time axis), with
    ``seeds`` (how many) and ``psnr_range`` (lowest, highest): one point per recipe, its spread drawn as a bar.
    Runs without a label, PSNR or seconds pass unchanged.

    Examples:
        >>> [(r["label"], r["psnr"], r.get("psnr_range")) for r in seed_means(
        ...     [{"label": "a", "psnr": 30.0, "seconds": 2.0}, {"label": "a-seed1", "psnr": 31.0, "seconds": 4.0},
        ...      {"label": "b", "psnr": 29.0, "seconds": 1.0}])]
        [('a', 30.5, (30.0, 31.0)), ('b', 29.0, None)]
    """
    scored = [r for r in runs if r.get("psnr") is not None and r.get("seconds") is not None]
    merged = [r for r in runs if r not in scored or not r.get("label")]
    for name, rows in seed_families(scored).items():
        if len(rows) == 1:
            merged.append(rows[0])
            continue
        psnrs = [r["psnr"] for r in rows]
        merged.append({**rows[0], "label": name, "seeds": len(rows), "psnr": sum(psnrs) / len(rows),
                       "seconds": sum(r["seconds"] for r in rows) / len(rows), "psnr_range": (min(psnrs), max(psnrs))})
    return merged


def _reconstruction_label(run: dict) -> str:
    size = f"{run['resolution']}³, " if run.get("resolution") else ""
    seeds = f", {run['seeds']} seeds" if run.get("seeds") else ""
    where = (", GPU" if device_kind(run) == "cuda" else "") + (", stale recipe" if run.get("stale") else "")
    return f"{run.get('label') or run.get('preset') or run.get('name')} ({size}{run.get('iterations')} it{seeds}{where})"


def _other_ground_truth(run: dict) -> str:
    other = "box" if run.get("resample") == "bilinear" else "bilinear"
    if run.get(f"psnr_{other}_gt") is None:
        return "–"
    return f"{other}: {run[f'psnr_{other}_gt']} / {fmt(run.get(f'ssim_{other}_gt'), 4)}"


def one_invocation(rows: list[dict]) -> bool:
    """Whether every row came from one invocation of the bench (its ``bench_run``): the shared machine's load and the
    code change between invocations, so only such rows compare as ratios of one run."""
    invocations = {r.get("bench_run") for r in rows}
    return len(invocations) == 1 and None not in invocations


def commits(rows: list[dict]) -> str:
    """The commits ``rows`` were measured at."""
    return " / ".join(sorted({r["commit"] for r in rows if r.get("commit")})) or "unrecorded commits"


def twin_means(runs: list[dict], pairs_of, title: str) -> list[str]:
    """One bullet setting each recipe beside its twin, each side the mean over its seeds: ``pairs_of(families)``
    gives (before label, after label, name); seconds only where every row of a pair came from one invocation of the
    bench (:func:`one_invocation`), else the commits each side was measured at."""
    families = seed_families(runs)
    pairs = pairs_of(families)
    if not pairs:
        return []

    def mean(rows: list[dict], key: str) -> float:
        return sum(r[key] for r in rows) / len(rows)

    parts = []
    for before, after, name in sorted(pairs, key=lambda p: p[2]):
        a, b = families[before], families[after]
        seeds = f"{len(a)} seed{'s' * (len(a) > 1)}" + ("" if len(a) == len(b) else f" / {len(b)}")
        at = f"both at {commits(a)}" if commits(a) == commits(b) else f"at {commits(a)} and {commits(b)}"
        seconds = (f"{mean(a, 'seconds'):.0f} vs {mean(b, 'seconds'):.0f} s" if one_invocation(a + b) else
                   f"measured in different runs, {at}: seconds not compared")
        parts.append(f"{name} {mean(a, 'psnr'):.2f} → {mean(b, 'psnr'):.2f} dB ({mean(b, 'psnr') - mean(a, 'psnr'):+.2f}; "
                     f"{seeds}; {seconds})")
    return [f"**{title}** (the same recipe, means over seeds): " + "; ".join(parts) + "."]


# Recipes that differ in one knob, as label suffixes of one recipe ``X`` (before, after), and what the bullet compares.
RECIPE_TWINS = (
    ("Rays from every image vs from 8 random images a step", (("", "-8-images"), ("-all-images", ""))),
    ("The early-stop density pass while training an object, on vs off", (("-early-stop", ""),)),
    ("2,000 steps of 4,096 rays at lr 0.03 vs 1,000 of 8,192 at lr 0.04 (the same samples in half the steps)",
     (("-4096-rays", ""),)),
)


def recipe_twin_tradeoffs(runs: list[dict]) -> list[str]:
    """One bullet per knob of ``RECIPE_TWINS``: each recipe whose twin was measured too (means over seeds)."""
    bullets = []
    for title, suffixes in RECIPE_TWINS:
        def pairs_of(families, suffixes=suffixes):
            return [(name + before, name + after, name) for before, after in suffixes for name in families
                    if name + before in families and name + after in families]

        bullets += twin_means(runs, pairs_of, title)
    return bullets


def reconstruction_tradeoffs(runs: list[dict]) -> list[str]:
    # Compare runs on one ground truth: the default filter's, where there are such runs.
    runs = [r for r in runs if r.get("resample") == "bilinear"] or runs
    bullets = []
    skipping = sorted((r for r in runs if r.get("skipping")), key=lambda r: (r.get("resolution", 0), r.get("iterations", 0)))
    by_res: dict = {}
    for r in skipping:
        by_res.setdefault(r.get("resolution"), []).append(r)
    if len(by_res) > 1:
        base = min(skipping, key=lambda r: r.get("seconds") or 0)
        best = [max(rs, key=lambda r: r.get("psnr") or 0) for rs in by_res.values()]
        apart = not one_invocation(best + [base])  # then no ratios: the commit each was measured at
        parts = [f"{r.get('resolution')}³: {r.get('psnr')} dB in {r.get('seconds')} s "
                 + (f"(at {commits([r])})" if apart else f"({ratio(r.get('seconds'), base.get('seconds'))} the fastest run)")
                 for r in best]
        across = "; measured in different runs, each at its commit" if apart else ""
        bullets.append(f"**Grid resolution** (reconstruction, skipping on, best run per size{across}): "
                       + "; ".join(parts) + ".")
    by_size: dict = {}  # one grid and one batch: what the iteration budget alone moves
    for r in skipping:
        if not SEED_SUFFIX.search(r.get("label", "")):
            by_size.setdefault((r.get("resolution"), r.get("rays_per_step")), []).append(r)
    for (res, rays), rs in by_size.items():
        if len({r.get("iterations") for r in rs}) > 1:
            apart = not one_invocation(rs)
            steps = ", ".join(f"{r.get('label')} {r.get('iterations')} it → {r.get('psnr')} dB in {r.get('seconds')} s"
                              + (f" (at {commits([r])})" if apart else "") for r in rs)
            batch = f", {rays:,} rays a step" if rays else ""
            across = "; measured in different runs, each at its commit: not ratios of one run" if apart else ""
            bullets.append(f"**Iteration budget** (reconstruction at {res}³{batch}, seed 0{across}): {steps}.")
    bullets += recipe_twin_tradeoffs(runs)
    for r in runs:
        if not r.get("skipping"):
            continue
        twin = next((d for d in runs if not d.get("skipping") and d.get("resolution") == r.get("resolution")
                     and d.get("iterations") == r.get("iterations")), None)
        if twin:
            bullets.append(
                f"**Skipping on/off while training** ({r.get('resolution')}³, {r.get('iterations')} it): dense takes "
                f"{ratio(twin.get('seconds'), r.get('seconds'))} the time ({twin.get('seconds')} s vs {r.get('seconds')} s) "
                f"for {twin.get('psnr')} dB vs {r.get('psnr')} dB.")
    rendered = [r for r in runs if r.get("render_time_ratio_dense_over_skip") is not None]
    if rendered:
        r = max(rendered, key=lambda r: r.get("resolution", 0))
        bullets.append(
            f"**Skipping on/off while rendering** (the same {r.get('resolution')}³ grid, run {r.get('label')}): "
            f"dense rendering evaluates {r.get('render_sample_ratio_dense_over_skip')}× the samples and takes "
            f"{r.get('render_time_ratio_dense_over_skip')}× the time, for PSNR {r.get('dense_render_psnr')} dB vs "
            f"{r.get('psnr')} dB with skipping.")
        bullets.append(
            "**Samples per ray** (grid evaluations per test ray, skipping vs dense, same grid): "
            + ", ".join(f"{x.get('label')} {x.get('samples_per_ray')} vs {x.get('dense_render_samples_per_ray')}"
                        for x in rendered)
            + "; PSNR moves by at most "
            + f"{max(abs((x.get('psnr') or 0) - (x.get('dense_render_psnr') or 0)) for x in rendered):.3f} dB. "
              "The sample spacing itself (`RenderConfig.step_ratio`) is not varied by any benchmark, so its accuracy "
              "cost is unmeasured.")
    return bullets


def segmentation_section(data, results: Path, report: Path) -> tuple[list[str], list[str]]:
    if not isinstance(data, dict) or not data.get("summary"):
        return ["No summary in the file."], []
    summary, runs = data["summary"], as_runs(data)
    settings = data.get("settings", {})
    noises = sorted({s["noise"] for s in summary})
    keys = sorted({(s["method"], s["scene"]) for s in summary})
    seconds = {}
    for r in runs:
        seconds.setdefault((r["method"], r["scene"]), []).append(r.get("seconds") or 0.0)
    lines = [
        data.get("description", ""), "",
        f"Settings: grid {settings.get('resolution')}³, {settings.get('views')} views of {settings.get('render_size')} px, "
        f"{settings.get('iterations')} lifting iterations, {settings.get('threads')} thread(s). Cells: mean 3D IoU "
        "(min over draws); seconds: mean per run (lifting + cut for `graph_cut`, lifting for `threshold_3d`, "
        "voting for `vote_2d`).", "",
    ]
    rows = []
    for method, scene in keys:
        cells = {s["noise"]: s for s in summary if (s["method"], s["scene"]) == (method, scene)}
        rows.append([method, scene] + [f"{cells[n]['iou_mean']:.3f} ({cells[n]['iou_min']:.3f})" if n in cells else "–"
                                       for n in noises]
                    + [significant(sum(seconds.get((method, scene), [0])) / max(1, len(seconds.get((method, scene), []))))])
    lines += table(["method", "scene"] + [f"IoU @ noise {n}" for n in noises] + ["s / run"], rows)
    graphs = [g for g in [data.get("graph_160"), *(data.get("graph_160_stress") or [])] if isinstance(g, dict)]
    if graphs:
        lines += ["", "Graph cut alone at the paper's 160³:", ""]
        lines += table(["case", "nodes", "edges", "build s", "solve s", "IoU vs truth"],
                       [[g.get("case", f"cow, field noise {g.get('field_noise')}"), g.get("nodes"), g.get("edges"),
                         fmt(g.get("build_s"), 3), fmt(g.get("solve_s"), 3), fmt(g.get("iou_vs_truth"), 4)]
                        for g in graphs])
    plot = results / "report_segmentation.png"
    plt = _pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    for i, (method, scene) in enumerate(keys):
        cells = sorted((s["noise"], s["iou_mean"]) for s in summary if (s["method"], s["scene"]) == (method, scene))
        left.plot([c[0] for c in cells], [c[1] for c in cells], marker="o", color=f"C{i}", label=f"{method} ({scene})")
    left.set_xlabel("map corruption strength")
    left.set_ylabel("3D IoU of the edit region")
    left.set_title("IoU vs noise")
    left.legend(fontsize=7)
    means = []
    for method, scene in keys:
        sel = [r for r in runs if (r["method"], r["scene"]) == (method, scene) and r.get("seconds") is not None]
        if sel:
            means.append({"label": f"{method} ({scene})", "device": sel[0].get("device"),
                          "seconds": sum(r["seconds"] for r in sel) / len(sel),
                          "iou": sum(r.get("iou") or 0.0 for r in sel) / len(sel)})
    right.scatter([r.get("seconds") for r in runs], [r.get("iou") for r in runs], color="0.8", s=8,
                  label="every run", zorder=1)
    layout = speed_error_axes(right, means, x="seconds", y="iou", label=lambda r: r["label"],
                              xlabel="seconds per run (log scale)", ylabel="3D IoU",
                              title="IoU vs seconds (mean over noise levels and draws)")
    lines += figure_link(fig, plot, report, "IoU vs noise and seconds", layout)
    bullets = []
    gc = [s for s in summary if s["method"] == "graph_cut" and s["scene"] == "distinct"]
    th = {s["noise"]: s for s in summary if s["method"] == "threshold_3d"}
    if gc and th and seconds.get(("graph_cut", "distinct")) and seconds.get(("threshold_3d", "any")):
        pairs = ", ".join(f"noise {s['noise']}: {s['iou_mean']:.3f} vs {th[s['noise']]['iou_mean']:.3f}"
                          for s in gc if s["noise"] in th)
        extra = (sum(seconds[("graph_cut", "distinct")]) / len(seconds[("graph_cut", "distinct")])
                 - sum(seconds[("threshold_3d", "any")]) / len(seconds[("threshold_3d", "any")]))
        bullets.append(f"**Graph cut on/off** (refinement): IoU with the cut vs thresholding P_e > 1/2 — {pairs}; the "
                       f"cut adds {extra:.2f} s per run on top of the lifting.")
    return lines, bullets


EDIT_PARTS = ("render", "vae", "unet", "backward", "optimizer", "other")


def _edit_label(run: dict) -> str:
    return run.get("name") or f"{run.get('model')} {run.get('device')} {run.get('dtype')} {run.get('resolution')}²"


def _edit_minutes(run: dict):
    """Projected 8,000-iteration minutes (bench/gpu.py writes them; older rows only ``ms_total``)."""
    ms = run.get("ms_total") or run.get("ms_step")
    return run.get("edit_8000_minutes") or (ms * 8000 / 60000 if ms else None)


def edit_step_section(data, gpu, results: Path, report: Path) -> tuple[list[str], list[str]]:
    """Edit-step rows of edit_step.json, then the GPU ones: ``gpu`` is edit_step_gpu.json's and gpu.json's runs."""
    rows = as_runs(data) + [r for r in gpu if r.get("kind", "edit_step") in ("edit_step", "edit")]
    if not rows:
        return ["No runs in the file."], []
    lines = [
        "Milliseconds per editing iteration split by part, averaged after warm-up. The models have RANDOM WEIGHTS "
        "(nothing can be downloaded here): these are costs only; no edit quality is measured, so no accuracy stands "
        "beside them — `what it buys` says what the timing means.", "",
    ]
    lines += table(["model", "device", "dtype", "guidance px", "render px", *[f"{p} ms" for p in EDIT_PARTS],
                    "total ms", "8000 it (min)", "what it buys"],
                   [[r.get("name") or r.get("model"), r.get("device"), r.get("dtype"),
                     r.get("resolution") or r.get("guidance_resolution"), r.get("render_size"),
                     *[fmt(r.get(f"ms_{p}"), 1) for p in EDIT_PARTS], fmt(r.get("ms_total") or r.get("ms_step"), 1),
                     fmt(_edit_minutes(r), 1), r.get("what_the_timing_buys", "")] for r in rows])
    plot = results / "report_edit_step.png"
    plt = _pyplot()
    fig, (parts, total) = plt.subplots(1, 2, figsize=(12, 1.8 + 0.55 * len(rows)), sharey=True,
                                       gridspec_kw={"width_ratios": [1.2, 1]})
    for j, part in enumerate(EDIT_PARTS):  # points on a log axis: parts span a millisecond to seconds
        timed = [(i, r[f"ms_{part}"] / 1000) for i, r in enumerate(rows) if (r.get(f"ms_{part}") or 0) > 0]
        parts.scatter([t for _, t in timed], [i for i, _ in timed], color=f"C{j}", s=18, label=part, zorder=3)
    steps = [(i, (r.get("ms_total") or r.get("ms_step")) / 1000) for i, r in enumerate(rows)
             if r.get("ms_total") or r.get("ms_step")]
    parts.scatter([t for _, t in steps], [i for i, _ in steps], color="black", marker="|", s=120,
                  label="whole step", zorder=4)
    parts.set_xscale("log")
    parts.grid(True, which="both", axis="x", color="0.92", linewidth=0.6)
    parts.set_yticks(range(len(rows)), [_edit_label(r) for r in rows], fontsize=8)
    parts.invert_yaxis()
    parts.set_xlabel("seconds per SDS iteration (log scale)")
    parts.set_title("Editing step: each part (where timed) and the whole")
    parts.legend(fontsize=7, loc="upper left")
    for kind, (marker, colour, name) in DEVICE_STYLE.items():
        mine = [(i, r) for i, r in enumerate(rows) if device_kind(r) == kind and _edit_minutes(r)]
        if mine:
            total.scatter([_edit_minutes(r) for _, r in mine], [i for i, _ in mine], marker=marker, s=40,
                          color=colour, label=name, zorder=3)
            for i, r in mine:
                total.annotate(f"   {_edit_minutes(r):,.0f} min", (_edit_minutes(r), i), fontsize=7, va="center")
    total.axvline(PAPER_EDIT_MINUTES, color="black", linestyle="--", linewidth=1,
                  label=f"paper: ~{PAPER_EDIT_MINUTES:.0f} min (8,000 it, RTX A5000)")
    total.set_xscale("log")
    total.margins(x=0.25)
    total.grid(True, which="both", axis="x", color="0.92", linewidth=0.6)
    total.set_xlabel("projected 8,000-iteration edit (minutes, log scale)")
    total.set_title("Whole edit at this speed\n(random weights: cost only)")
    total.legend(fontsize=7, loc="lower right")
    lines += figure_link(fig, plot, report, "seconds per SDS iteration by part")
    bullets = []
    for r in rows:
        if r.get("ms_total"):
            budgets = ", ".join(f"{n} it ≈ {r['ms_total'] * n / 60000:.0f} min" for n in (2000, 4000, 8000))
            bullets.append(f"**Edit iteration budget** ({r.get('model')}, {r.get('device')} {r.get('dtype')}, "
                           f"{r.get('resolution')}² guidance): {budgets} (linear in the iterations; what fewer "
                           "iterations cost in edit quality is unmeasured: no real weights here).")
    dtypes = {(r.get("device"), r.get("dtype")) for r in rows}
    if not any(d == "cuda" for d, _ in dtypes):
        bullets.append(
            "**fp16 vs fp32**: no GPU measurement exists (no `edit_step_gpu.json`; run `python bench/edit_step.py --gpu` "
            "on a CUDA machine), so the speed of fp16 is unmeasured here. Accuracy, measured on CPU by "
            "`tests/test_hard_cases.py` on the tiny random model: under bf16 autocast the SDS latent gradient moves "
            "by 8–9 % relative L2 at guidance scale 100 (3 % at 7.5; test tolerance 15 %); the renderer and the "
            "regulariser compute in fp32 under autocast, bit-identical to fp32.")
    return lines, bullets  # with GPU runs, gpu_section compares the dtypes (same run, same model)


GPU_TARGETS = (  # issue 17's, on one H200 with full-size random-weight models
    ("8,000-iteration edit (the default)", "≤ 4 min", lambda runs: _default_edit(runs, "edit_8000_minutes"),
     lambda v: v <= 4, "{:.1f} min"),
    ("refinement at 160³", "≤ 1 min", lambda runs: _pick(runs, "refinement", "seconds"), lambda v: v <= 60, "{:.1f} s"),
    ("whole local-edit job (8,000 it)", "≤ 6 min",
     lambda runs: _minutes(_pick(runs, "job", "seconds_projected_8000_iterations")), lambda v: v <= 6, "{:.1f} min"),
    ("`fast` reconstruction of mic", "≤ 20 s", lambda runs: _preset(runs, "fast", "seconds"), lambda v: v <= 20, "{:.1f} s"),
    ("`paper` reconstruction of mic", "≤ 2 min", lambda runs: _preset(runs, "paper", "seconds"), lambda v: v <= 120,
     "{:.1f} s"),
    ("`paper` reconstruction PSNR", "≥ 30.6 dB", lambda runs: _preset(runs, "paper", "psnr"), lambda v: v >= 30.6,
     "{:.2f} dB"),
    # Section b's loop (the edit alone in its process). A graph's replay allocates nothing, so where CUDA graphs ran
    # max_memory_allocated leaves their pools out and would flatter the figure: the reserved peak counts them.
    ("peak GPU memory of the default edit", "≤ 24 GB", lambda runs: _default_edit_memory(runs),
     lambda v: v <= 24 / 1.073741824, "{:.2f} GiB"),
)


def _pick(runs: list[dict], kind: str, key: str, pick=min):
    """``pick`` (the best: min; the worst: max) of ``key`` over ``runs`` of ``kind`` rendered as the defaults render
    (:func:`_default_marcher`); None when none has it."""
    values = [r[key] for r in runs if r.get("kind") == kind and r.get(key) is not None and _default_marcher(r)]
    return pick(values) if values else None


DEFAULT_FUSED_MARCHER = False  # voxe_core's RenderConfig().fused (tests/test_bench_report.py holds them equal)


def _default_marcher(run: dict) -> bool:
    """Whether ``run``'s renders marched as the defaults march them (bench/gpu.py's ``--fused-marcher`` rows say
    ``fused_marcher``): the targets are the defaults'."""
    return bool(run.get("fused_marcher", False)) == DEFAULT_FUSED_MARCHER


def _default_edit(runs: list[dict], key: str):
    """``key`` of section b's loop (the default edit) from the latest device call that ran it."""
    loops = [r for r in runs if r.get("section") == "b" and r.get("kind") == "edit" and r.get(key) is not None
             and _default_marcher(r)]
    return max(loops, key=lambda r: r.get("call", 0))[key] if loops else None


def _default_edit_memory(runs: list[dict]):
    """The default edit's peak: reserved where its CUDA graphs ran (their pools), else allocated."""
    graphed = _default_edit(runs, "cuda_graphs")
    return _default_edit(runs, "peak_memory_reserved_gb" if graphed else "peak_memory_gb")


def _minutes(seconds):
    return None if seconds is None else seconds / 60


def _preset_run(runs: list[dict], preset: str) -> dict | None:
    """The preset's own run (not a variant of it timed beside it)."""
    return next((r for r in runs if r.get("kind") == "reconstruction" and r.get("preset") == preset
                 and "variant" not in r), None)


def _preset(runs: list[dict], preset: str, key: str):
    return (_preset_run(runs, preset) or {}).get(key)


RECIPE_KEYS = ("rays_per_step", "lr", "iterations", "images_per_step", "early_stop")
"""What a fit's row records of its recipe (bench/reconstruction.py's rows, bench/gpu.py's section c)."""
# What bench/gpu.py's preset fits ran before their rows recorded it: 2,000 steps at lr 0.03 from every image with the
# early-stop density pass while training.
UNRECORDED_RECIPES = {preset: {"rays_per_step": rays, "lr": 0.03, "iterations": 2000, "images_per_step": 0,
                               "early_stop": 1e-4} for preset, rays in (("fast", 4096), ("paper", 32768))}
# Per preset: the CPU's rows of the preset as it is, and the nearest they have to what the GPU's fits ran before they
# recorded it (the paper's from every image is measured without the pass).
STALE_FIT_TWINS = {"fast": ("preset-fast", "preset-fast-4096-rays-all-images-early-stop"),
                   "paper": ("preset-paper", "preset-paper-all-images")}


def _recipe(run: dict, unrecorded: dict | None = None) -> dict:
    return {key: run.get(key, (unrecorded or {}).get(key)) for key in RECIPE_KEYS}


def describe_recipe(recipe: dict) -> str:
    """A fit's recipe in words, e.g. "1,000 steps of 8,192 rays at lr 0.04 from 8 images, no early-stop pass"."""
    drawn = f"from {recipe['images_per_step']} images" if recipe["images_per_step"] else "from every image"
    probed = "with the early-stop pass" if recipe["early_stop"] else "no early-stop pass"
    return f"{recipe['iterations']:,} steps of {recipe['rays_per_step']:,} rays at lr {recipe['lr']} {drawn}, {probed}"


def stale_gpu_runs(gpu_runs: list[dict], cpu_runs: list[dict]) -> list[tuple[str, dict, dict, dict]]:
    """(preset, its GPU run, the recipe that ran, the preset's recipe now) for each GPU preset fit whose recipe is not
    its preset's as the CPU's rows of it ran (a row from before fits recorded theirs ran ``UNRECORDED_RECIPES``')."""
    families = seed_families(cpu_runs)
    stale = []
    for preset, (now, _) in STALE_FIT_TWINS.items():
        run = _preset_run(gpu_runs, preset)
        if run is None or not families.get(now):
            continue
        ran, current = _recipe(run, UNRECORDED_RECIPES[preset]), _recipe(families[now][0])
        if ran != current and None not in current.values():  # not the same, and CPU rows that say what they ran
            stale.append((preset, run, ran, current))
    return stale


def _stale_gpu_fits(gpu_runs: list[dict], cpu_runs: list[dict]) -> list[str]:
    """A line under the targets for each stale GPU preset fit (:func:`stale_gpu_runs`), with the CPU's figures of both
    recipes (means over seeds): what its rerun moves. The CPU's rows of the recipe the GPU ran are the preset's variant
    that ran it, or else ``STALE_FIT_TWINS``' nearest."""
    families = seed_families(cpu_runs)
    lines = []
    for preset, run, ran, current in stale_gpu_runs(gpu_runs, cpu_runs):
        now, nearest = STALE_FIT_TWINS[preset]
        before = next((name for name, rows in families.items() if name.startswith(now) and _recipe(rows[0]) == ran),
                      nearest)  # among the preset's own variants: another recipe may share these five knobs
        named = [(now, current)] + ([(before, _recipe(families[before][0]))] if families.get(before) else [])
        measured = "; ".join(f"{sum(r['psnr'] for r in families[name]) / len(families[name]):.2f} dB with "
                             f"{describe_recipe(recipe)} (`{name}`, {len(families[name])} "
                             f"seed{'s' * (len(families[name]) > 1)})" for name, recipe in named)
        lines.append(f"The GPU's `{preset}` run ({run['psnr']:.2f} dB) ran {describe_recipe(ran)}: the preset is now "
                     f"{describe_recipe(current)}, so it is rerun at the next device call. On the CPU: {measured}.")
    return [line for text in lines for line in ("", text)]


def gpu_section(gpu, reconstruction, results: Path, report: Path) -> tuple[list[str], list[str]]:
    """(section lines, trade-off bullets) from gpu.json (bench/gpu.py on the lent GPU machine): its runs, issue 17's
    targets against them, and the speed-ups' ratios."""
    runs = [r for r in as_runs(gpu) if device_kind(r) == "cuda" and "error" not in r]
    if not runs:
        return ["**No results:** `results/gpu.json` is missing: `bench/gpu.py` runs only on a lent CUDA machine "
                "(`bench/gpu_carry.sh`, then `bench/gpu_device.sh` there)."], []
    calls = gpu.get("calls") if isinstance(gpu, dict) else None
    lines = [f"Source: `{relative(results / 'gpu.json', report)}` (see `bench/gpu.py`), on {gpu.get('device')} with "
             f"torch {gpu.get('torch')}. Full-size SD-2-base- and SD-1.4-shaped models with RANDOM WEIGHTS: the "
             "times are costs only; the reconstruction's PSNR/SSIM are real (mic's test views).", ""]
    if calls:
        lines += ["Device calls (one session's 15 minutes of device time, so sections are split over calls and each "
                  "run names its call):", ""] + [f"- call {k}: {v}" for k, v in calls.items()] + [""]
    notes = list(dict.fromkeys(r["note"] for r in runs if r.get("note")))  # a run's caveat, numbered under the table
    lines += table(["section", "call", "run", "dtype", "CUDA graphs", "ms/step", "8000 it (min)", "seconds", "PSNR dB",
                    "SSIM", "peak GiB"],
                   [[r.get("section"), r.get("call"), r.get("name") + (f" [{notes.index(r['note']) + 1}]" if
                                                                        r.get("note") else ""),
                     r.get("dtype"), r.get("cuda_graphs", "–"), fmt(r.get("ms_step"), 1),
                     fmt(r.get("edit_8000_minutes"), 1), fmt(r.get("seconds"), 1), fmt(r.get("psnr"), 2),
                     fmt(r.get("ssim"), 4), fmt(r.get("peak_memory_gb"), 2)] for r in runs])
    lines += [""] + [f"- [{n}] {note}." for n, note in enumerate(notes, 1)] if notes else []
    # The CPU's `fast` preset over its seeds: another device draws other random numbers, so its PSNR is compared
    # with their mean, their range beside it.
    cpu_fast = [r for r in as_runs(reconstruction)
                if SEED_SUFFIX.sub("", r.get("label", "")) == "preset-fast" and "psnr" in r]
    gpu_fast = _preset_run(runs, "fast")
    target_rows = []
    for name, target, measure, met, form in GPU_TARGETS:
        value = measure(runs)
        target_rows.append([name, target, "–" if value is None else form.format(value),
                            "not measured" if value is None else ("met" if met(value) else "**not met**")])
    if cpu_fast and gpu_fast:
        psnrs = [r["psnr"] for r in cpu_fast]
        mean = sum(psnrs) / len(psnrs)
        same_size = {r.get("image_size") for r in cpu_fast} == {gpu_fast.get("image_size")}
        verdict = ("met" if gpu_fast["psnr"] >= mean else "**not met**") if same_size else \
            f"not comparable: {gpu_fast.get('image_size')} px on the GPU, {cpu_fast[0].get('image_size')} px on the CPU"
        spread = f"; seeds {min(psnrs):.2f}–{max(psnrs):.2f}" if len(psnrs) > 1 else ""
        target_rows.append(["`fast` PSNR against the CPU's",
                            f"≥ {mean:.2f} dB (CPU `preset-fast`, mean of {len(psnrs)} seed{'s' * (len(psnrs) > 1)}"
                            f"{spread})", f"{gpu_fast['psnr']:.2f} dB", verdict])
    lines += ["", "Issue 17's targets:", ""] + table(["target", "asked", "measured", "verdict"], target_rows)
    lines += _stale_gpu_fits(runs, as_runs(reconstruction))
    lines += figure_link_png(results / "gpu.png", report, "GPU stages")
    bullets = []
    steps = {r["name"]: r for r in runs if r.get("kind") == "edit_step"}
    fp32 = next((r for r in steps.values() if r.get("dtype") == "float32"), None)
    fp16 = next((r for r in steps.values() if r.get("dtype") == "float16" and r.get("half")), None)
    if fp32 and fp16:
        difference = fp16.get("sds_grad_relative_difference")
        accuracy = (f"In the same run the fp16 SDS gradient differs from the fp32 one by {difference:.2g} of its "
                    f"largest entry on the same inputs (the gradient sent to the renders by "
                    f"{fp16['encoder_image_grad_relative_difference']:.2g})." if difference is not None else
                    "What fp16 costs in accuracy on the GPU is pending the next device run (bench/gpu.py's section a "
                    "records the fp16 SDS gradient's difference from the fp32 baseline's since these rows were "
                    "measured); so far it is measured only on the CPU, under bf16 autocast on the tiny random model "
                    "(`tests/test_hard_cases.py`, not this run): the SDS latent gradient moves by 8–9 % relative L2 "
                    "at guidance scale 100 (3 % at 7.5).")
        bullets.append(f"**fp16 vs fp32** (GPU speed, same run): the SDS step takes {fp16['ms_step']:.1f} ms in fp16 "
                       f"against {fp32['ms_step']:.1f} ms in fp32 ({fp32['ms_step'] / fp16['ms_step']:.2f}×) and "
                       f"{fp16['peak_memory_gb']:.2f} against {fp32['peak_memory_gb']:.2f} GiB at its peak. {accuracy}")
    graph_steps = [r for r in steps.values() if r.get("section") == "g"]
    eager = next((r for r in graph_steps if r.get("cuda_graphs") is False), None)
    graphed = next((r for r in graph_steps if r.get("cuda_graphs") is True), None)
    if eager and graphed:
        bullets.append(f"**CUDA graphs** (GPU, same run): the step takes {graphed['ms_step']:.1f} ms against "
                       f"{eager['ms_step']:.1f} eager ({eager['ms_step'] / graphed['ms_step']:.2f}×); the UNet part "
                       f"{graphed['ms_unet']:.1f} against {eager['ms_unet']:.1f} ms; the graphed SDS gradient differs "
                       f"from the eager one by {graphed.get('sds_grad_relative_difference', float('nan')):.1g} and "
                       "the gradient it sends to the renders by "
                       f"{graphed.get('encoder_image_grad_relative_difference', float('nan')):.1g} (relative to their "
                       "largest entries).")
    bullets += render_pass_tradeoffs([r for r in runs if r.get("kind") == "render_passes"])
    bullets += interpolation_tradeoffs([r for r in runs if r.get("kind") == "interpolation"])
    bullets += fused_marcher_tradeoffs(runs)
    bullets += reconstruction_variants(runs)
    bullets += step_speedups(runs)
    bullets += step_profile(runs)
    launch = next((r for r in runs if r.get("ms_unet_batch_2") and r.get("ms_unet_batch_8")), None)
    if launch:
        bullets.append(f"**The eager UNet is launch-bound**: the eager fp16 UNet forward takes "
                       f"{launch['ms_unet_batch_2']:.1f} ms at batch 2 and {launch['ms_unet_batch_8']:.1f} ms at "
                       f"batch 8 ({launch['batch_8_over_batch_2']:.2f}×): four times the work in the same time, so the "
                       "host launching kernels, not the GPU's arithmetic, sets the pace; the renderer and the backward "
                       "(Python-driven, data-dependent shapes) are the larger share left after the graphs.")
    return lines, bullets


def step_speedups(runs: list[dict]) -> list[str]:
    """Bullets for the GPU step's later speed-ups: render passes sized for the device (section i), the compiled VAE
    encoder (section j, with the default loop's warm-up from section b) and where the default step's time goes."""
    bullets = []
    passes = [r for r in runs if r.get("section") == "i" and r.get("samples_per_pass")]
    default = next((r for r in passes if "(default)" in r["name"]), None)
    if passes and default:
        base = passes[0]
        moved = max((r["max_rgb_difference"] for r in runs if r.get("kind") == "render_passes"
                     and device_kind(r) == "cuda"), default=None)
        same = "" if moved is None else f" (section h: no pixel moves by more than {moved:.1g}, float32 rounding)"
        bullets.append(f"**Render passes sized for the device** (GPU, same run): the step takes {default['ms_step']:.1f} ms "
                       f"with passes of 2^{default['samples_per_pass'].bit_length() - 1} samples against "
                       f"{base['ms_step']:.1f} ms with the CPU's 2^20 ({default['speedup_over_2_20']:.2f}×), the "
                       f"render {default['ms_render']:.1f} against {base['ms_render']:.1f} ms; the same render{same}.")
    no_stop = next((r for r in passes if r.get("early_stop") == 0), None)
    if no_stop and default:
        bullets.append(f"**Early stopping on the GPU** (same run): the step takes {no_stop['ms_step']:.1f} ms without "
                       f"it against {default['ms_step']:.1f} ms with it ({default['ms_step'] / no_stop['ms_step']:.2f}×), "
                       f"the render {no_stop['ms_render']:.1f} against {default['ms_render']:.1f} ms and its backward "
                       f"{no_stop['ms_backward_render']:.1f} against {default['ms_backward_render']:.1f} ms; "
                       f"{no_stop['samples_per_ray']:.0f} against {default['samples_per_ray']:.0f} grid evaluations a "
                       "ray (with it, the density probe's included); without it no pixel moves by more than the "
                       "1e-4 threshold (tests/test_render.py).")
    encoders = [r for r in runs if r.get("section") == "j" and "ms_step" in r]
    eager = next((r for r in encoders if r.get("compile_encoder") is False), None)
    compiled = next((r for r in encoders if r.get("compile_encoder") and not r.get("graphed_encoder")), None)
    compile_seconds = _default_edit(runs, "warm_seconds") if _default_edit(runs, "compile_encoder") else None
    if eager and compiled:
        warm = "" if compile_seconds is None else \
            f"; its compile took {compile_seconds:.0f} s of the loop's warm-up, once per guidance"
        bullets.append(f"**Compiled VAE encoder** (GPU, same run): the step takes {compiled['ms_step']:.1f} ms against "
                       f"{eager['ms_step']:.1f} with the graphed eager encoder "
                       f"({eager['ms_step'] / compiled['ms_step']:.2f}×): the encoder's forward "
                       f"{compiled['ms_vae']:.1f} against {eager['ms_vae']:.1f} ms, the backward up to the renders "
                       f"(the encoder's and the regulariser's) {compiled['ms_backward_guidance']:.1f} against "
                       f"{eager['ms_backward_guidance']:.1f} ms{warm}. "
                       f"The encoder's latents move by {compiled['encoder_latents_relative_difference']:.1g} and the "
                       f"gradient it sends to the renders by {compiled['encoder_image_grad_relative_difference']:.1g} "
                       "(relative to their largest entries; fp16 kernels fused differently).")
        parts = ", ".join(f"{label} {compiled[key]:.1f}" for label, key in (
            ("render", "ms_render"), ("VAE encoder", "ms_vae"), ("UNet", "ms_unet"),
            ("encoder + regulariser backward", "ms_backward_guidance"), ("render backward", "ms_backward_render"),
            ("Adam", "ms_optimizer")))
        bullets.append(f"**Where the default step's time goes** (GPU, device times, ms): {parts}.")
    return bullets


def step_profile(runs: list[dict]) -> list[str]:
    """A bullet from section k's profile of the default step (the latest call's): how much of the step the device
    spends computing, what a step launches and waits for, and its longest kernels and host operations."""
    profiles = [r for r in runs if r.get("kind") == "step_profile" and r.get("device_busy_ms_per_step") is not None]
    if not profiles:
        return []
    run = max(profiles, key=lambda r: r.get("call") or 0)

    def top(key: str) -> str:
        return "; ".join(f"{e['name']} {e['ms_per_step']:.2f} ms ({e['calls_per_step']:.0f}×)" for e in run[key][:5])

    return [f"**Where the step's time goes, profiled** (GPU, torch.profiler, which lengthens the host's share): the "
            f"device computes {run['device_busy_ms_per_step']:.1f} ms of a {run['profiled_ms_step']:.1f} ms step "
            f"({run['device_busy_fraction']:.0%}); a step launches {run['kernel_launches_per_step']:.0f} kernels and "
            f"waits for the device {run['host_synchronisations_per_step']:.0f} times. Longest kernels: "
            f"{top('top_kernels')}. Largest host self times: {top('top_host_operations')}."]


def by_scene_and_device(runs: list[dict]):
    """(scene, device, its rows) for each scene and device of a render bench's rows, in first-seen order (rows without
    a device were measured on the CPU)."""
    for scene, device in dict.fromkeys((r["scene"], r.get("device", "cpu")) for r in runs):
        yield scene, device, [r for r in runs if r["scene"] == scene and r.get("device", "cpu") == device]


def render_pass_tradeoffs(runs: list[dict]) -> list[str]:
    """One bullet per scene and device of bench/render_passes.py's rows: each pass size against the CPU's default."""
    bullets = []
    for scene, device, mine in by_scene_and_device(runs):
        mine = sorted(mine, key=lambda r: r["samples_per_pass"])
        figures = "; ".join(
            f"2^{r['samples_per_pass'].bit_length() - 1}: {r['operations_ratio_to_reference']:.2f}× the operations, "
            f"{r['ms_ratio_to_reference']:.2f}× the time, {fmt(r.get('peak_memory_gb'), 2)} GiB" for r in mine[1:])
        bullets.append(f"**Samples per render pass** ({scene}, {device}; against the CPU's default 2^"
                       f"{mine[0]['samples_per_pass'].bit_length() - 1}: {mine[0]['operations']} operations, "
                       f"{mine[0]['ms']:.0f} ms, {fmt(mine[0].get('peak_memory_gb'), 2)} GiB): {figures}; the render "
                       f"moves by at most {max(r['max_rgb_difference'] for r in mine):.1g}.")
    return bullets


def fused_marcher_tradeoffs(runs: list[dict]) -> list[str]:
    """bench/gpu.py's section l: per scene the fused marcher's render and backward against the packed renderer's,
    then the step and the loop with it, each beside what it moved in the render and the gradient."""
    bullets = []
    renders = [r for r in runs if r.get("kind") == "fused_render"]
    for scene, device, mine in by_scene_and_device(renders):
        packed = next((r for r in mine if r["marcher"] == "packed"), None)
        fused = next((r for r in mine if r["marcher"] == "fused"), None)
        if packed and fused:
            bullets.append(
                f"**Fused ray marcher** ({scene}, {device}; the edit's render and backward): {fused['ms']:.1f} ms "
                f"against the packed renderer's {packed['ms']:.1f} ({packed['ms'] / fused['ms']:.2f}×), "
                f"{fused['operations']} operations against {packed['operations']}, {fused['samples']:,} grid "
                f"evaluations against {packed['samples']:,}; the render moves by {fused['max_rgb_difference']:.1g}, "
                f"the gradient by {fused['max_gradient_difference']:.1g} of its largest entry.")
    steps = [r for r in runs if r.get("section") == "l" and r.get("kind") == "edit_step" and "ms_step" in r]
    loop = next((r for r in runs if r.get("section") == "b" and r.get("kind") == "edit" and "ms_step" in r
                 and r.get("fused_marcher")), None)  # --fused-marcher's loop
    if len(steps) == 2:
        packed, fused = steps
        looped = (f"; {loop['iterations']} iterations with it: {loop['ms_step']:.1f} ms each, "
                  f"{loop['edit_8000_minutes']:.1f} min projected to 8,000" if loop else "")
        bullets.append(f"**Fused ray marcher in the edit step** (same run): {fused['ms_step']:.1f} ms against "
                       f"{packed['ms_step']:.1f} ({fused['speedup_over_packed']:.2f}×), its render "
                       f"{fmt(fused.get('ms_render'), 1)} against {fmt(packed.get('ms_render'), 1)} ms{looped}.")
    return bullets


def reconstruction_variants(runs: list[dict]) -> list[str]:
    """One bullet per reconstruction variant timed beside its preset's own run (bench/gpu.py section c)."""
    bullets = []
    for variant in (r for r in runs if r.get("kind") == "reconstruction" and "variant" in r):
        preset = _preset_run(runs, variant["preset"])
        if preset is None or preset.get("call") != variant.get("call"):
            continue
        bullets.append(f"**`{variant['preset']}` with {variant['variant']}** ({variant['device']}, same run): "
                       f"{variant['seconds']:.1f} s against {preset['seconds']:.1f} s as the preset is "
                       f"({variant['seconds_over_default']:.2f}×), test PSNR {variant['psnr']:.2f} against "
                       f"{preset['psnr']:.2f} dB.")
    return bullets


def interpolation_tradeoffs(runs: list[dict]) -> list[str]:
    """One bullet per scene and device of bench/interpolation.py's rows: each variant against the default."""
    bullets = []
    for scene, device, mine in by_scene_and_device(runs):
        default = next((r for r in mine if r["variant"] == "default"), None)
        if default is None:
            continue
        figures = "; ".join(
            f"{r['variant']}: forward {r['forward_ratio_to_default']:.2f}×, backward "
            f"{r['backward_ratio_to_default']:.2f}×, both {r['ms_ratio_to_default']:.2f}× the default's time, "
            f"{r['saved_for_backward_mb']:.0f} MB kept for the backward, gradient within "
            f"{r['max_gradient_difference']:.1g} of the default's" for r in mine if r is not default)
        bullets.append(f"**The interpolation in the edit's render** ({scene}, {device}, {default['samples']:,} grid "
                       f"evaluations; the default: forward {default['forward_ms']:.1f} ms, backward "
                       f"{default['backward_ms']:.1f} ms, {default['saved_for_backward_mb']:.0f} MB kept): {figures}.")
    return bullets


def figure_link_png(path: Path, report: Path, alt: str) -> list[str]:
    """A link to a plot a benchmark drew itself (none when it is absent)."""
    return ["", f"![{alt}]({relative(path, report)})"] if path.is_file() else []


def service_load_section(data, results: Path, report: Path) -> tuple[list[str], list[str]]:
    if not isinstance(data, dict):
        return ["The file is not a JSON object."], []
    phases = [p for p in ("submit", "status_during_submit", "status", "status_without_streams")
              if isinstance(data.get(p), dict)]
    streams = data.get("streams") or {}
    lines = [data.get("what", ""), "",
             f"{data.get('pollers')} pollers, {data.get('submitters')} submitters, {streams.get('requested', 0)} event "
             f"streams open during `status` (none during `status_without_streams`; p99 ratio with / without: "
             f"{data.get('status_p99_with_over_without_streams')}). Correctness beside speed: errors per "
             "phase, and jobs accepted but not listed or not queued (lost).", ""]
    lines += table(["phase", "requests", "req/s", "p50 ms", "p90 ms", "p99 ms", "max ms", "errors"],
                   [[p, data[p].get("requests"), data[p].get("requests_per_s"), fmt(data[p].get("p50_ms"), 1),
                     fmt(data[p].get("p90_ms"), 1), fmt(data[p].get("p99_ms"), 1), fmt(data[p].get("max_ms"), 1),
                     data[p].get("errors")] for p in phases])
    lines += ["", f"Jobs accepted {data.get('jobs_accepted')}, listed {data.get('jobs_listed')}, queued in the broker "
                  f"{data.get('jobs_queued_in_broker')}, lost {data.get('lost_jobs')}; targets "
                  f"({', '.join(f'{k} {v}' for k, v in (data.get('targets') or {}).items())}) met: "
                  f"{data.get('targets_note') or data.get('targets_met')}."]
    if phases:
        plot = results / "report_service_load.png"
        plt = _pyplot()
        fig, ax = plt.subplots(figsize=(7, 3.8))
        for j, q in enumerate(("p50_ms", "p90_ms", "p99_ms")):
            ax.bar([i + 0.27 * (j - 1) for i in range(len(phases))], [data[p].get(q) or 0 for p in phases],
                   width=0.27, label=q.replace("_ms", ""))
        for i, p in enumerate(phases):
            ax.annotate(f"{data[p].get('errors')} errors", (i, 0), xycoords=("data", "axes fraction"), fontsize=7,
                        xytext=(0, -22), textcoords="offset points", ha="center")
        target = (data.get("targets") or {}).get("status_p99_ms")
        if target:
            ax.axhline(target, color="black", linestyle="--", linewidth=1, label=f"target: status p99 ≤ {target:g} ms")
        ax.set_yscale("log")  # latencies span milliseconds to a second
        ax.set_axisbelow(True)
        ax.grid(True, which="both", axis="y", color="0.92", linewidth=0.6)
        ax.set_xticks(range(len(phases)), phases, fontsize=8)
        ax.set_ylabel("latency (ms, log scale)")
        ax.set_title("Service: request latency by phase")
        ax.legend(fontsize=7)
        lines += figure_link(fig, plot, report, "latency by phase")
    return lines, []


MAX_ROWS = 40  # rows of a results file's table in REPORT.md


def scalar_table(rows: list[dict]) -> list[str]:
    """``rows``' scalar fields (at most 12 columns) as a markdown table; none when no field is scalar in all."""
    columns = [k for k in dict.fromkeys(k for r in rows for k in r)
               if all(isinstance(r.get(k), (int, float, str, bool, type(None))) for r in rows)][:12]
    if not rows or not columns:
        return []
    cell = lambda v: f"{v:.4g}" if isinstance(v, float) else v  # noqa: E731
    return table(columns, [[cell(r.get(k)) for k in columns] for r in rows])


def producer(path: Path, data) -> str:
    """The script that writes a results file: the one its description names ("see bench/x.py"), else the
    longest script whose name is its stem or starts it (``localisation_160`` -> ``bench/localisation.py``),
    else ``bench/<stem>.py``."""
    named = re.search(r"see (bench/\w+\.py)", data.get("description", "") if isinstance(data, dict) else "")
    if named:
        return named.group(1)
    scripts = sorted((p.stem for p in HERE.glob("*.py")), key=len, reverse=True)
    return f"bench/{next((s for s in scripts if path.stem == s or path.stem.startswith(s + '_')), path.stem)}.py"


def other_results_section(results: Path, report: Path) -> list[str]:
    """Results of benchmarks outside the four stages (e.g. real scenes), shown as their scalar fields and own plot."""
    known = {stage.result for stage in STAGES} | {"edit_step_gpu.json", "gpu.json"}
    lines = []
    for path in sorted(results.glob("*.json")):
        data = load_json(path)
        if path.name in known or data is None:
            continue
        runs = as_runs(data)
        summary = data.get("summary") if isinstance(data, dict) else None
        lines += [f"### `{path.stem}`", "", f"Source: `{relative(path, report)}` (see `{producer(path, data)}`); "
                  "its scalar fields as written, speed and accuracy side by side in each row.", ""]
        if isinstance(summary, list) and summary and all(isinstance(r, dict) for r in summary):
            lines += ["Its summary:", ""] + scalar_table(summary) + [""]
        lines += scalar_table(runs[:MAX_ROWS])
        lines += [f"(the first {MAX_ROWS} of {len(runs)} rows; all of them in the JSON)", ""] if len(runs) > MAX_ROWS \
            else [""]
        scalars = [f"- {k}: {fmt(v, 3)}" for k, v in summary.items()
                   if not isinstance(v, (dict, list))] if isinstance(summary, dict) else []
        lines += scalars + [""] if scalars else []
        if path.with_suffix(".png").is_file():
            lines += [f"![{path.stem}]({relative(path.with_suffix('.png'), report)})", ""]
    return (["## Other benchmark results", ""] + lines) if lines else []


# ------------------------------------------------------------------ report


def build_report(results: Path, report: Path, notes: dict[str, str], mode: str) -> str:
    stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    out = [
        "# Speed against error: the whole pipeline",
        "",
        f"Generated by `python bench/report.py {mode}` on {stamp} from `{relative(results, HERE)}/*.json`. "
        "Each speed figure stands beside the accuracy measured in the same run; timings come from a shared CPU, so "
        "compare them within one table (as ratios), not across tables or machines. Regenerate with "
        "`python bench/report.py --collect-only` after re-running any benchmark.",
        "",
    ]
    tradeoffs: list[str] = []
    gpu = load_json(results / "gpu.json")  # bench/gpu.py on the device machine; absent until it has run
    for stage in STAGES:
        out += [f"## {stage.title}", ""]
        path = results / stage.result
        data = load_json(path)
        if stage.name in notes:
            out += [f"**Not measured in this run:** {notes[stage.name]}", ""]
            if data is not None:
                out += [f"The figures below are the previous record in `{relative(path, report)}`.", ""]
        if data is None:
            if stage.name not in notes:
                out += [f"**No results:** `{relative(path, report)}` is missing or unreadable; run "
                        f"`python bench/{stage.script}` (or `bench/report.py --quick`).", ""]
            continue
        out += [f"Source: `{relative(path, report)}`.", ""]
        try:
            if stage.name == "reconstruction":
                lines, bullets = reconstruction_section(data, gpu, results, report)
            elif stage.name == "segmentation":
                lines, bullets = segmentation_section(data, results, report)
            elif stage.name == "edit_step":
                lines, bullets = edit_step_section(
                    data, as_runs(load_json(results / "edit_step_gpu.json")) + as_runs(gpu), results, report)
            else:
                lines, bullets = service_load_section(data, results, report)
        except (KeyError, TypeError, ValueError, AttributeError) as error:  # a benchmark changed its schema
            lines, bullets = [f"**Could not summarise** `{relative(path, report)}` ({type(error).__name__}: {error}); "
                              f"bench/report.py needs updating to its current layout."], []
        out += lines + [""]
        tradeoffs += bullets
    out += ["## The GPU path on the lent device machine (issue 17)", ""]
    gpu_lines, gpu_bullets = gpu_section(gpu or {}, load_json(results / "reconstruction.json"), results, report)
    out += gpu_lines + [""]
    tradeoffs += gpu_bullets + render_pass_tradeoffs(as_runs(load_json(results / "render_passes.json")))
    tradeoffs += interpolation_tradeoffs(as_runs(load_json(results / "interpolation.json")))
    out += other_results_section(results, report)
    out += ["## Trade-offs a user chooses between", ""]
    out += [f"- {b}" for b in tradeoffs] or ["- No benchmark results to draw them from."]
    measured_by = {"Grid resolution": "reconstruction", "Iteration budget": "reconstruction and edit_step",
                   "Skipping": "reconstruction", "Samples per ray": "reconstruction", "fp16 vs fp32": "edit_step"}
    for name, scripts in measured_by.items():
        if not any(name.lower() in b.lower() for b in tradeoffs):
            out.append(f"- **{name}**: not measured here: no result of `bench/{scripts.replace(' and ', '.py` / `bench/')}.py` "
                       "that measures it is present.")
    return "\n".join(out).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--collect-only", action="store_true", help="only read bench/results/*.json")
    mode.add_argument("--quick", action="store_true", help="run every stage at CI size (results in bench/results/quick/)")
    mode.add_argument("--full", action="store_true", help="run every stage at full size (hours on 2 cores)")
    parser.add_argument("--stages", nargs="*", choices=[s.name for s in STAGES], help="stages to run (default: all)")
    parser.add_argument("--timeout", type=float, default=None, help="seconds per stage benchmark (default: none)")
    parser.add_argument("--out", type=Path, default=None, help="report path (default bench/REPORT.md; quick: in its folder)")
    args = parser.parse_args(argv)
    results = QUICK_RESULTS if args.quick else RESULTS
    report = args.out or (results / "REPORT.md" if args.quick else REPORT)
    results.mkdir(parents=True, exist_ok=True)
    notes: dict[str, str] = {}
    if not args.collect_only:
        for stage in STAGES:
            if args.stages and stage.name not in args.stages:
                continue
            note = run_stage(stage, args.quick, results, args.timeout)
            if note:
                notes[stage.name] = note
                print(f"[report] {stage.name}: {note}", file=sys.stderr)
    flag = "--quick" if args.quick else "--full" if args.full else "--collect-only"
    report.parent.mkdir(parents=True, exist_ok=True)
    report.write_text(build_report(results, report, notes, flag))
    print(f"wrote {report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
