"""Grid files sparse against dense at 128³: bytes, save and load seconds, and what the round trip changes.

The grids are the real inputs: NeRF-synthetic mic and the fox capture
reconstructed with the ``fast`` preset (final stage 128³; fox on the scene
backbone), and the spot and horse meshes voxelised at 128³. Each grid is
written dense (``dense=True``, today's 33.5 MB) and sparse at several margins
(the default, ``voxe_core.gridfile.DEFAULT_MARGIN``, is the row that counts),
then loaded back and every feature read once, ``--repeats`` times (median
seconds; a dense file is memory-mapped, so loading alone would read nothing). In the same run: whether
every stored vertex is bit-identical, and the largest pixel difference of
renders of the loaded grid against the original (with and without empty-space
skipping). For comparison, the bytes a brick layout (8³-vertex bricks holding
any stored vertex) would take. Writes bench/results/grid_files.json and .png.

    nice python bench/grid_files.py              # ~10 min on 2 shared cores (two fast-preset fits)
    nice python bench/grid_files.py --quick      # short fits, same grid size (fox's scene fit is the long one)
    nice python bench/grid_files.py --only mic spot horse   # rerun some; the other grids' saved rows are kept
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
DATA = HERE.parent.parent / "shared" / "data"
RESULTS = HERE / "results"
MARGINS = (0, 1, 2, 4)
GRIDS = ("mic", "fox", "spot", "horse")
BRICK = 8


def scene_grids(args) -> dict:
    """name -> 128³ grid: two reconstructions and two voxelised meshes."""
    from reconstruction import WITHOUT_CAPTURE_PRIORS, as_measured

    from voxe_core.backbones import prepare_backbone
    from voxe_core.data import load_scene
    from voxe_core.mesh_input import VoxelizeConfig, load_mesh, voxelize
    from voxe_core.reconstruct import ReconstructConfig, reconstruct

    grids = {}
    iterations = (60, 100, 200) if args.quick else (300, 500, 1200)
    for name, folder, downsample in (("mic", "nerf_synthetic_mic", 4), ("fox", "fox", 4)):
        if name not in args.only:
            continue
        scene = load_scene(DATA / folder, "train", downsample=downsample)
        # fast()'s recipe before 2026-12-05 (4,096 rays a step at lr 0.03 from every image, the early-stop pass):
        # what the records were measured with.
        config = ReconstructConfig.fast(resolutions=(args.resolution // 3, args.resolution // 3 * 2, args.resolution),
                                        iterations=iterations, rays_per_step=4096, lr=0.03)
        backbone, cameras, initial = prepare_backbone("auto", scene.alphas, scene.cameras, config.resolutions[0])
        # ... and without the priors a capture's fit has kept since 2026-12-05 (the fox record's grid had none).
        config = dataclasses.replace(as_measured(config.for_backbone(backbone)), **WITHOUT_CAPTURE_PRIORS)
        t0 = time.perf_counter()
        grids[name] = reconstruct(scene.images, cameras, config, initial_grid=initial)
        print(f"{name}: {backbone} grid fitted in {time.perf_counter() - t0:.0f} s", flush=True)
    for name, obj, texture in (("spot", "spot/spot_triangulated.obj", "spot/spot_texture.png"), ("horse", "horse/horse.obj", None)):
        if name not in args.only:
            continue
        mesh = load_mesh(DATA / "meshes" / obj, None if texture is None else DATA / "meshes" / texture)
        grids[name] = voxelize(mesh, VoxelizeConfig(resolution=args.resolution))
    return grids


def read_all(path):
    """``load_grid`` and one read of every feature (a dense file is memory-mapped: loading alone reads nothing)."""
    from voxe_core.backbones import load_grid

    grid = load_grid(path)
    grid.features.detach().sum()
    return grid


def timed(fn, repeats: int) -> tuple[float, object]:
    seconds, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        seconds.append(time.perf_counter() - t0)
    return statistics.median(seconds), result


def render_difference(a, b, skip_empty: bool) -> float:
    from voxe_core.export import turntable_cameras
    from voxe_core.render import RenderConfig, render_image

    cameras = turntable_cameras(2, size=64)
    config = RenderConfig(skip_empty=skip_empty)
    return max(float((render_image(a, cameras, i, config).rgb - render_image(b, cameras, i, config).rgb).abs().max())
               for i in range(len(cameras)))


def measure(name: str, grid, folder: Path, repeats: int) -> list[dict]:
    from voxe_core.gridfile import stored_vertices

    cells = (grid.occupancy_above(0.0) if grid.activation == "relu" else grid.occupancy()).cells
    rows = []
    dense_path = folder / f"{name}_dense.safetensors"
    save_s, _ = timed(lambda: grid.save(dense_path, dense=True), repeats)
    load_s, _ = timed(lambda: read_all(dense_path), repeats)
    dense_bytes = dense_path.stat().st_size
    rows.append({"grid": name, "backbone": grid.kind, "layout": "dense", "margin": None, "bytes": dense_bytes,
                 "save_s": save_s, "load_s": load_s, "occupied_fraction": float(cells.float().mean()),
                 "stored_fraction": 1.0, "stored_exact": True, "render_max_diff": 0.0, "render_max_diff_skip": 0.0})
    for margin in MARGINS:
        path = folder / f"{name}_sparse{margin}.safetensors"
        save_s, _ = timed(lambda: grid.save(path, margin=margin), repeats)
        load_s, loaded = timed(lambda: read_all(path), repeats)
        kept = stored_vertices(cells, margin)
        block_any = torch.nn.functional.pad(kept, [0, -kept.shape[2] % BRICK, 0, -kept.shape[1] % BRICK,
                                                   0, -kept.shape[0] % BRICK])
        bricks = int(block_any.unflatten(0, (-1, BRICK)).unflatten(2, (-1, BRICK)).unflatten(4, (-1, BRICK))
                     .any(5).any(3).any(1).sum())
        rows.append({
            "grid": name, "backbone": grid.kind, "layout": "sparse", "margin": margin, "bytes": path.stat().st_size,
            "save_s": save_s, "load_s": load_s, "occupied_fraction": float(cells.float().mean()),
            "stored_fraction": float(kept.float().mean()),
            "brick_layout_bytes": bricks * (BRICK**3 * 16 + 4),
            "stored_exact": bool(torch.equal(loaded.features.detach()[kept], grid.features.detach()[kept])),
            "render_max_diff": render_difference(loaded, grid, skip_empty=False),
            "render_max_diff_skip": render_difference(loaded, grid, skip_empty=True),
        })
    for row in rows:
        row["bytes_ratio"] = row["bytes"] / dense_bytes
        row["load_ratio"] = row["load_s"] / rows[0]["load_s"]
    return rows


def plot(rows: list[dict], default_margin: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["grid"] for r in rows))
    dense = [next(r for r in rows if r["grid"] == n and r["layout"] == "dense") for n in names]
    sparse = [next(r for r in rows if r["grid"] == n and r["margin"] == default_margin) for n in names]
    fig, (ax_bytes, ax_load) = plt.subplots(1, 2, figsize=(10, 4))
    x = range(len(names))
    for ax, key, scale, label in ((ax_bytes, "bytes", 1e-6, "file size (MB)"), (ax_load, "load_s", 1e3, "load_grid (ms)")):
        shown = [key != "load_s" or "note" not in r for r in dense]
        ax.bar([i - 0.2 for i in x], [r[key] * scale * k for r, k in zip(dense, shown)], 0.4, label="dense",
               color="tab:gray")
        ax.bar([i + 0.2 for i in x], [r[key] * scale * k for r, k in zip(sparse, shown)], 0.4,
               label=f"sparse, margin {default_margin}", color="tab:green")
        for i, (d, s) in enumerate(zip(dense, sparse)):
            if key == "load_s" and "note" in s:  # timed by an older loader (see the JSON's notes): not comparable
                ax.annotate("see notes", (i, ax.get_ylim()[0]), ha="center", fontsize=8, textcoords="offset points",
                            xytext=(0, 3))
                continue
            ax.annotate(f"{s[key] / d[key]:.3f}x", (i + 0.2, s[key] * scale), ha="center", fontsize=8,
                        textcoords="offset points", xytext=(0, 3))
        ax.set_xticks(list(x), [f"{n}\n{d['occupied_fraction']:.1%} occ." for n, d in zip(names, dense)])
        ax.set_yscale("log")
        ax.set_ylabel(label)
        ax.legend(fontsize=8)
    ax_bytes.set_title("128³ grid files: bytes (renders identical)")
    ax_load.set_title("load + read every feature, median (2 shared cores)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    from voxe_core.gridfile import DEFAULT_MARGIN

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="short reconstructions (same grid size)")
    parser.add_argument("--only", nargs="+", choices=GRIDS, default=list(GRIDS),
                        help="measure these grids; the saved rows of the others are kept")
    args = parser.parse_args()
    torch.set_num_threads(os.cpu_count() or 1)
    saved = RESULTS / "grid_files.json"
    rows = [r for r in json.loads(saved.read_text())["rows"] if r["grid"] not in args.only] if saved.exists() else []
    with tempfile.TemporaryDirectory() as folder:
        for name, grid in scene_grids(args).items():
            for row in measure(name, grid, Path(folder), args.repeats):
                rows.append({**row, "quick": args.quick})
                print(f"{row['grid']:6s} {row['layout']:6s} margin {row['margin']!s:4s} {row['bytes'] / 1e6:8.3f} MB "
                      f"({row['bytes_ratio']:.4f}x)  save {row['save_s'] * 1e3:7.1f} ms  load {row['load_s'] * 1e3:7.1f} ms "
                      f"({row['load_ratio']:.2f}x)  occupied {row['occupied_fraction']:.2%}  stored {row['stored_fraction']:.2%}  "
                      f"exact {row['stored_exact']}  render diff {row['render_max_diff']:.1e} / skip {row['render_max_diff_skip']:.1e}",
                      flush=True)
    default = [r for r in rows if r["margin"] == DEFAULT_MARGIN]
    summary = {
        "default_margin": DEFAULT_MARGIN,
        "bytes_ratio": {r["grid"]: r["bytes_ratio"] for r in default},
        "load_ratio": {r["grid"]: r["load_ratio"] for r in default},
        "brick_over_mask_bytes": {r["grid"]: r["brick_layout_bytes"] / r["bytes"] for r in default},
        "all_exact_and_identical": all(r["stored_exact"] and r["render_max_diff"] == 0 and r["render_max_diff_skip"] == 0
                                       for r in rows),
    }
    print(json.dumps(summary, indent=1))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "grid_files.json").write_text(json.dumps({"args": vars(args), "rows": rows, "summary": summary}, indent=1))
    plot(rows, DEFAULT_MARGIN, RESULTS / "grid_files.png")


if __name__ == "__main__":
    main()
