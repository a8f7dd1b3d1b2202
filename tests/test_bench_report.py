"""bench/report.py: the Pareto front, label placement and the plots on a small synthetic record (no benchmark runs)."""

import json
import sys
from pathlib import Path

import pytest
import torch
from needs import DATA_ROOT, MIC, needs_data

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import report  # noqa: E402 - bench/ is on the path only from here; matplotlib, which it plots with, is a dev dependency


def test_pareto_front_keeps_exactly_the_undominated_points():
    # (seconds, PSNR): (3, 2) is beaten by (2, 3); (2, 1) ties in time with (2, 3) but is worse; (5, 4) ties in
    # quality with (4, 4) but is slower.
    points = [(1, 1), (2, 3), (3, 2), (4, 4), (2, 1), (5, 4)]
    assert report.pareto_front(points) == [0, 1, 3]
    assert report.pareto_front([]) == []


def test_labels_never_overlap_and_separate_ones_stay_level():
    anchors = [(0, 0), (10, 3), (20, 5), (500, 0)]
    ys = report.place_labels(anchors, [100, 100, 100, 100], 8)
    assert ys[3] == 0  # far to the right: nothing to avoid
    crowded = sorted(ys[:3])
    assert all(b - a >= 8 * (1 - 1e-9) for a, b in zip(crowded, crowded[1:]))
    assert all(abs(y - anchor[1]) <= 2 * 8 for y, anchor in zip(ys, anchors))  # within two heights of its point
    # a crowd on one point spreads above and below it, nearest slots first (not all of it upwards)
    assert sorted(report.place_labels([(0, 0)] * 5, [100] * 5, 8)) == [-16, -8, 0, 8, 16]


def test_report_plots_cpu_and_gpu_runs_and_handles_a_missing_gpu_json(tmp_path):
    recon = [{"label": f"r{i}", "resolution": 64, "iterations": 100 * i, "skipping": True, "resample": "bilinear",
              "seconds": 10.0 * i, "psnr": 25.0 + i * (1 if i % 2 else -1)} for i in range(1, 6)]
    edit = [{"model": "tiny", "device": "cpu", "dtype": "float32", "resolution": 64, "ms_render": 10.0,
             "ms_total": 30.0}]
    (tmp_path / "reconstruction.json").write_text(json.dumps(recon))
    (tmp_path / "edit_step.json").write_text(json.dumps(edit))
    out = tmp_path / "REPORT.md"
    text = report.build_report(tmp_path, out, {}, "--collect-only")  # no gpu.json
    assert (tmp_path / "report_reconstruction.png").stat().st_size > 0
    assert (tmp_path / "report_edit_step.png").stat().st_size > 0
    assert "Could not summarise" not in text
    gpu = {"runs": [{"name": "reconstruction mic fast", "kind": "reconstruction", "device": "cuda", "seconds": 5.0,
                     "psnr": 29.0, "iterations": 300},
                    {"name": "edit_loop", "kind": "edit", "device": "cuda", "dtype": "float16", "ms_step": 20.0,
                     "edit_8000_minutes": 20.0 * 8000 / 60000}]}
    (tmp_path / "gpu.json").write_text(json.dumps(gpu))
    text = report.build_report(tmp_path, out, {}, "--collect-only")
    assert "Could not summarise" not in text and "edit_loop" in text
    assert report.device_kind({"device": "cuda:0"}) == "cuda" and report.device_kind({}) == "cpu"


def test_a_table_cell_holding_a_newline_or_a_pipe_keeps_its_row_whole():
    """bench/cli_startup.py's stderr column (a refusal and its newline) had broken its REPORT row in two."""
    lines = report.table(["case", "stderr", "seconds"], [["refused", "voxe: error: a | b\n", 0.5], ["ok", "", None]])
    assert lines[2:] == [r"| refused | voxe: error: a \| b | 0.50 |", "| ok |  | – |"]


def test_every_results_file_names_a_script_that_exists():
    from report import producer

    results = Path(__file__).resolve().parents[1] / "bench" / "results"
    for path in results.glob("*.json"):
        script = producer(path, json.loads(path.read_text()))
        assert (results.parent.parent / script).is_file(), (path.name, script)
    assert producer(Path("localisation_160.json"), {}) == "bench/localisation.py"  # the longest script prefix
    assert producer(Path("localisation_grids_fox.json"), {}) == "bench/localisation_grids.py"
    assert producer(Path("x.json"), {"description": "…; see bench/real_scenes.py --compare-lens"}) == "bench/real_scenes.py"


def test_a_long_results_file_shows_its_summary_and_its_first_rows(tmp_path):
    runs = [{"case": f"c{i}", "iou": i / 100} for i in range(report.MAX_ROWS + 10)]
    summary = [{"case": "all", "mean_iou": 0.245}]
    (tmp_path / "long_bench.json").write_text(json.dumps({"runs": runs, "summary": summary}))
    text = "\n".join(report.other_results_section(tmp_path, tmp_path / "REPORT.md"))
    assert "| all | 0.245 |" in text and f"(the first {report.MAX_ROWS} of {len(runs)} rows" in text
    assert f"| c{report.MAX_ROWS - 1} |" in text and f"| c{report.MAX_ROWS} |" not in text


def test_gpu_section_reads_issue_17s_targets_and_ratios_from_gpu_json(tmp_path):
    gpu = {"device": "NVIDIA H200", "torch": "2.x", "calls": {"1": "a, b"}, "runs": [
        {"name": "fp32", "kind": "edit_step", "section": "a", "device": "cuda", "dtype": "float32", "half": False,
         "ms_step": 120.0, "peak_memory_gb": 8.0},
        {"name": "fp16", "kind": "edit_step", "section": "a", "device": "cuda", "dtype": "float16", "half": True,
         "ms_step": 100.0, "peak_memory_gb": 4.0},
        {"name": "eager", "kind": "edit_step", "section": "g", "device": "cuda", "dtype": "float16",
         "cuda_graphs": False, "ms_step": 90.0, "ms_unet": 40.0, "note": "a peak with a second model loaded"},
        {"name": "graphs", "kind": "edit_step", "section": "g", "device": "cuda", "dtype": "float16",
         "cuda_graphs": True, "ms_step": 60.0, "ms_unet": 10.0, "sds_grad_relative_difference": 0.0,
         "encoder_image_grad_relative_difference": 0.002},
        {"name": "loop", "kind": "edit", "section": "b", "call": 1, "device": "cuda", "edit_8000_minutes": 5.0,
         "peak_memory_gb": 30.0},
        {"name": "loop, graphs", "kind": "edit", "section": "b", "call": 2, "device": "cuda", "cuda_graphs": True,
         "edit_8000_minutes": 3.5, "peak_memory_gb": 2.0, "peak_memory_reserved_gb": 26.0},
        {"name": "compiled encoder", "kind": "edit_step", "section": "j", "device": "cuda", "dtype": "float16",
         "cuda_graphs": False, "ms_step": 45.0, "ms_unet": 30.0},
        {"name": "loop beside another model", "kind": "edit", "section": "g", "device": "cuda",
         "edit_8000_minutes": 1.0},
        {"name": "job", "kind": "job", "section": "f", "device": "cuda", "seconds_projected_8000_iterations": 420.0},
        {"name": "fast", "kind": "reconstruction", "section": "c", "device": "cuda", "preset": "fast", "seconds": 12.0,
         "psnr": 30.0, "image_size": 200},
        {"name": "broken", "kind": "refinement", "section": "d", "device": "cuda", "error": "RuntimeError: x"},
    ]}
    cpu = [{"label": "preset-fast", "psnr": 29.5, "image_size": 200},
           {"label": "preset-fast-seed1", "psnr": 30.5, "image_size": 200}, {"label": "fast-64", "psnr": 40.0},
           {"label": "preset-fast-8-images", "psnr": 35.0, "image_size": 200}]  # a variant, not the preset
    lines, bullets = report.gpu_section(gpu, cpu, tmp_path, tmp_path / "REPORT.md")
    text = "\n".join(lines)
    assert "| 8,000-iteration edit (the default) | ≤ 4 min | 3.5 min | met |" in text  # b's latest call
    assert "| g | – | eager [1] |" in text and "\n- [1] a peak with a second model loaded.\n" in text  # its note
    assert "| whole local-edit job (8,000 it) | ≤ 6 min | 7.0 min | **not met** |" in text
    assert "| refinement at 160³ | ≤ 1 min | – | not measured |" in text  # a failed run is no measurement
    # the latest default loop ran CUDA graphs: their pools count (reserved), not the allocated 2.0 GiB
    assert "| peak GPU memory of the default edit | ≤ 24 GB | 26.00 GiB | **not met** |" in text
    assert ("| `fast` PSNR against the CPU's | ≥ 30.00 dB (CPU `preset-fast`, mean of 2 seeds; seeds 29.50–30.50) "
            "| 30.00 dB | met |") in text
    (fp16,) = [b for b in bullets if "fp16 vs fp32" in b]
    assert "(1.20×)" in fp16 and "pending the next device run" in fp16  # no same-run accuracy in these rows
    gpu["runs"][1].update(sds_grad_relative_difference=0.0123, encoder_image_grad_relative_difference=0.004)
    (fp16,) = [b for b in report.gpu_section(gpu, cpu, tmp_path, tmp_path / "REPORT.md")[1] if "fp16 vs fp32" in b]
    assert "the fp16 SDS gradient differs from the fp32 one by 0.012 of its largest entry" in fp16
    assert "pending" not in fp16 and "test_hard_cases" not in fp16
    assert any("CUDA graphs" in b and "(1.50×)" in b and "10.0 against 40.0 ms" in b for b in bullets)
    cpu[0]["image_size"] = cpu[1]["image_size"] = 266
    text = "\n".join(report.gpu_section(gpu, cpu, tmp_path, tmp_path / "REPORT.md")[0])
    assert "not comparable: 200 px on the GPU, 266 px on the CPU" in text
    assert "**No results:**" in report.gpu_section({}, cpu, tmp_path, tmp_path / "REPORT.md")[0][0]


def test_render_pass_tradeoffs_compare_each_pass_size_with_the_cpus_default():
    rows = [{"scene": "sphere", "device": "cpu", "samples_per_pass": 1 << 20, "operations": 1200, "ms": 600.0,
             "peak_memory_gb": 0.7, "operations_ratio_to_reference": 1.0, "ms_ratio_to_reference": 1.0,
             "max_rgb_difference": 0.0},
            {"scene": "sphere", "device": "cpu", "samples_per_pass": 1 << 22, "operations": 600, "ms": 720.0,
             "peak_memory_gb": 1.1, "operations_ratio_to_reference": 0.5, "ms_ratio_to_reference": 1.2,
             "max_rgb_difference": 0.0}]
    (bullet,) = report.render_pass_tradeoffs(rows)
    assert "(sphere, cpu; against the CPU's default 2^20: 1200 operations, 600 ms, 0.70 GiB)" in bullet
    assert "2^22: 0.50× the operations, 1.20× the time, 1.10 GiB" in bullet and "at most 0" in bullet


def test_issue_17s_targets_read_the_default_marchers_rows_only():
    """A ``--fused-marcher`` call's loop and job are not the defaults' (until the fused marcher is the default)."""
    from voxe_core.render import RenderConfig

    assert report.DEFAULT_FUSED_MARCHER == RenderConfig().fused
    packed = {"section": "b", "kind": "edit", "call": 5, "edit_8000_minutes": 8.1}
    fused = {**packed, "call": 7, "edit_8000_minutes": 3.9, "fused_marcher": True}
    jobs = [{"kind": "job", "seconds_projected_8000_iterations": 516.0},
            {"kind": "job", "seconds_projected_8000_iterations": 300.0, "fused_marcher": True}]
    assert report._default_edit([packed, fused], "edit_8000_minutes") == 8.1
    assert report._pick(jobs, "job", "seconds_projected_8000_iterations") == 516.0


def test_fused_marcher_bullets_set_it_against_the_packed_renderer_beside_what_it_moved():
    render = {"kind": "fused_render", "scene": "sphere", "device": "cuda", "max_gradient_difference": 0.0}
    runs = [{**render, "marcher": "packed", "ms": 26.0, "operations": 900, "samples": 3_000_000,
             "max_rgb_difference": 0.0},
            {**render, "marcher": "fused", "ms": 2.0, "operations": 120, "samples": 1_000_000,
             "max_rgb_difference": 2e-7, "max_gradient_difference": 3e-6},
            {"section": "l", "kind": "edit_step", "ms_step": 60.0, "ms_render": 22.0, "speedup_over_packed": 1.0},
            {"section": "l", "kind": "edit_step", "ms_step": 40.0, "ms_render": 2.0, "speedup_over_packed": 1.5},
            {"section": "b", "kind": "edit", "iterations": 500, "ms_step": 61.0, "edit_8000_minutes": 8.1},
            {"section": "b", "kind": "edit", "iterations": 500, "ms_step": 39.0, "edit_8000_minutes": 5.2,
             "fused_marcher": True}]
    render_bullet, step_bullet = report.fused_marcher_tradeoffs(runs)
    assert "(sphere, cuda; the edit's render and backward): 2.0 ms against the packed renderer's 26.0 (13.00×)" in \
        render_bullet
    assert "1,000,000 grid evaluations against 3,000,000; the render moves by 2e-07, the gradient by 3e-06" in \
        render_bullet
    assert step_bullet == ("**Fused ray marcher in the edit step** (same run): 40.0 ms against 60.0 (1.50×), its "
                           "render 2.0 against 22.0 ms; 500 iterations with it: 39.0 ms each, 5.2 min projected to "
                           "8,000.")
    assert report.fused_marcher_tradeoffs(runs[:1]) == []  # a scene measured with one marcher only: no comparison


def test_interpolation_bullets_set_each_variant_against_the_default_per_scene_and_device():
    row = {"scene": "sphere", "samples": 1_900_000, "saved_for_backward_mb": 28.0, "max_gradient_difference": 0.0,
           "forward_ms": 400.0, "backward_ms": 80.0}
    ratios = {"forward_ratio_to_default": 1.0, "backward_ratio_to_default": 1.0, "ms_ratio_to_default": 1.0}
    rows = [{**row, **ratios, "device": "cpu", "variant": "default"},
            {**row, "device": "cpu", "variant": "embedding backward", "forward_ratio_to_default": 1.01,
             "backward_ratio_to_default": 1.66, "ms_ratio_to_default": 1.12},
            {**row, **ratios, "device": "cuda", "variant": "mul-sum forward"}]  # no default on cuda: no bullet
    (bullet,) = report.interpolation_tradeoffs(rows)
    assert "(sphere, cpu, 1,900,000 grid evaluations; the default: forward 400.0 ms, backward 80.0 ms" in bullet
    assert "embedding backward: forward 1.01×, backward 1.66×, both 1.12× the default's time" in bullet


def test_step_speedups_compare_pass_sizes_and_encoders_within_their_sections():
    runs = [
        {"name": "edit_step samples_per_pass 2^20", "section": "i", "samples_per_pass": 1 << 20, "ms_step": 90.0,
         "ms_render": 30.0, "speedup_over_2_20": 1.0},
        {"name": "edit_step samples_per_pass 2^22 (default)", "section": "i", "samples_per_pass": 1 << 22,
         "ms_step": 75.0, "ms_render": 20.0, "speedup_over_2_20": 1.2, "early_stop": 1e-4, "ms_backward_render": 4.0,
         "samples_per_ray": 30.0},
        {"name": "edit_step samples_per_pass 2^22, early_stop 0", "section": "i", "samples_per_pass": 1 << 22,
         "ms_step": 60.0, "ms_render": 12.0, "speedup_over_2_20": 1.5, "early_stop": 0.0, "ms_backward_render": 5.0,
         "samples_per_ray": 24.0},
        {"kind": "render_passes", "device": "cuda", "max_rgb_difference": 2e-7},
        {"name": "loop", "section": "b", "kind": "edit", "compile_encoder": True, "warm_seconds": 39.0},
        {"name": "eager encoder", "section": "j", "compile_encoder": False, "graphed_encoder": True, "ms_step": 72.0,
         "ms_vae": 14.0, "ms_backward_guidance": 19.0},
        {"name": "compiled", "section": "j", "compile_encoder": True, "graphed_encoder": False, "ms_step": 60.0,
         "ms_vae": 6.0, "ms_backward_guidance": 16.0, "ms_render": 22.0, "ms_unet": 10.0, "ms_backward_render": 4.0,
         "ms_optimizer": 0.5, "encoder_latents_relative_difference": 0.003,
         "encoder_image_grad_relative_difference": 0.005},
    ]
    passes, early_stop, compiled, parts = report.step_speedups(runs)
    assert ("60.0 ms without it against 75.0 ms with it (1.25×), the render 12.0 against 20.0 ms and its backward "
            "5.0 against 4.0 ms; 24 against 30 grid evaluations") in early_stop
    assert "75.0 ms with passes of 2^22 samples against 90.0 ms with the CPU's 2^20 (1.20×)" in passes
    assert "no pixel moves by more than 2e-07" in passes
    assert "60.0 ms against 72.0 with the graphed eager encoder (1.20×)" in compiled
    assert ("forward 6.0 against 14.0 ms, the backward up to the renders (the encoder's and the regulariser's) 16.0 "
            "against 19.0 ms; its compile took 39 s") in compiled
    assert parts.endswith("render 22.0, VAE encoder 6.0, UNet 10.0, encoder + regulariser backward 16.0, render "
                          "backward 4.0, Adam 0.5.")
    assert report.step_speedups([]) == []


def test_step_profile_reads_the_latest_calls_device_share_and_top_entries():
    def profile(call, busy):
        return {"kind": "step_profile", "call": call, "profiled_ms_step": 80.0, "device_busy_ms_per_step": busy,
                "device_busy_fraction": busy / 80.0, "kernel_launches_per_step": 1234.0,
                "host_synchronisations_per_step": 9.0,
                "top_kernels": [{"name": f"kernel{i}", "ms_per_step": 1.0 / (i + 1), "calls_per_step": 2.0}
                                for i in range(8)],
                "top_host_operations": [{"name": "aten::index_select", "ms_per_step": 3.0, "calls_per_step": 40.0}]}

    (bullet,) = report.step_profile([profile(8, 36.0), profile(7, 50.0),
                                     {"kind": "step_profile", "device_busy_ms_per_step": None, "call": 9}])
    assert "the device computes 36.0 ms of a 80.0 ms step (45%)" in bullet
    assert "launches 1234 kernels and waits for the device 9 times" in bullet
    assert "kernel0 1.00 ms (2×); kernel1 0.50 ms" in bullet and "kernel5" not in bullet  # the five longest
    assert "aten::index_select 3.00 ms (40×)" in bullet
    assert report.step_profile([]) == []


def test_recipe_twins_pair_each_recipe_with_its_twin_over_seeds():
    def row(label, psnr, seconds=10.0, bench_run="a"):
        return {"label": label, "psnr": psnr, "seconds": seconds, "bench_run": bench_run}

    runs = [row("recipe", 29.0), row("recipe-seed1", 30.0), row("recipe-8-images", 31.0),
            row("recipe-8-images-seed1", 31.5, 20.0), row("paper", 32.0, bench_run="b"), row("paper-all-images", 30.5),
            row("unpaired", 40.0), {"psnr": 1.0}]
    (bullet,) = report.recipe_twin_tradeoffs(runs)
    assert bullet.startswith("**Rays from every image vs from 8 random images a step**")
    assert "recipe 29.50 → 31.25 dB (+1.75; 2 seeds; 10 vs 15 s)" in bullet
    assert ("paper 30.50 → 32.00 dB (+1.50; 1 seed; measured in different runs, both at unrecorded commits: seconds "
            "not compared)") in bullet  # two invocations
    assert "unpaired" not in bullet and "recipe-8-images" not in bullet
    assert report.recipe_twin_tradeoffs([row("recipe", 29.0)]) == []
    images, early_stop, rays = report.recipe_twin_tradeoffs(
        runs + [row("recipe-early-stop", 29.0, 12.0), row("recipe-early-stop-seed1", 29.2, 12.0),
                row("recipe-4096-rays", 29.4, 20.0)])
    assert images == bullet
    assert "early-stop density pass" in early_stop and "recipe 29.10 → 29.50 dB (+0.40; 2 seeds; 12 vs 10 s)" in early_stop
    assert "half the steps" in rays and "recipe 29.40 → 29.50 dB (+0.10; 1 seed / 2; 20 vs 10 s)" in rays


def test_a_reconstruction_variant_is_set_against_its_presets_run_of_the_same_call():
    def fit(seconds, psnr, call=7, **extra):
        return {"kind": "reconstruction", "preset": "fast", "device": "cuda", "seconds": seconds, "psnr": psnr,
                "call": call, **extra}

    variant = fit(21.0, 30.61, variant="the early-stop pass", seconds_over_default=21.0 / 18.0)
    (bullet,) = report.reconstruction_variants([fit(18.0, 30.6), variant])
    assert bullet == ("**`fast` with the early-stop pass** (cuda, same run): 21.0 s against 18.0 s as the preset is "
                      "(1.17×), test PSNR 30.61 against 30.60 dB.")
    assert report.reconstruction_variants([fit(18.0, 30.6, call=4), variant]) == []  # another call's run
    assert report._preset_run([variant, fit(18.0, 30.6)], "fast")["seconds"] == 18.0  # the preset's own run


def test_seed_means_merge_each_recipes_seeds_into_one_point_with_its_range():
    runs = [{"label": "a", "psnr": 30.0, "seconds": 2.0, "resolution": 64}, {"label": "a-seed2", "psnr": 31.0, "seconds": 4.0},
            {"label": "a-seed1-box", "psnr": 20.0, "seconds": 1.0}, {"label": "gpu", "psnr": 29.0, "seconds": 1.0},
            {"label": "unscored", "seconds": 1.0}, {"psnr": 28.0, "seconds": 1.0}]
    merged = {r.get("label"): r for r in report.seed_means(runs)}
    assert set(merged) == {"a", "a-seed1-box", "gpu", "unscored", None}  # the box copy is another recipe (a-box)
    assert (merged["a"]["psnr"], merged["a"]["seconds"], merged["a"]["psnr_range"], merged["a"]["seeds"]) == \
        (30.5, 3.0, (30.0, 31.0), 2)
    assert report._reconstruction_label(merged["a"]) == "a (64³, None it, 2 seeds)"
    assert "psnr_range" not in merged["gpu"]


def test_a_crowd_of_points_is_numbered_and_listed_beside_the_axes():
    plt = report._pyplot()
    runs = [{"label": f"run-{i}", "seconds": 10.0 + i, "psnr": 30.0} for i in range(12)]
    fig, ax = plt.subplots(figsize=(6, 4))
    layout = report.speed_error_axes(ax, runs, x="seconds", y="psnr", label=lambda r: r["label"], xlabel="s",
                                     ylabel="dB", title="t")
    assert [t.get_text() for t in ax.texts] == [str(n) for n in range(1, 13)]
    listed = fig.texts[-1]
    assert listed.get_text().splitlines()[::11] == [" 1  run-0", "12  run-11"]
    fig.canvas.draw()
    assert layout[2] < 1 and listed.get_window_extent().x0 > ax.get_window_extent().x1  # right of the axes
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 4))
    assert report.speed_error_axes(ax, runs[:10], x="seconds", y="psnr", label=lambda r: r["label"], xlabel="s",
                                   ylabel="dB", title="t") == (0, 0, 1, 1)
    assert [t.get_text() for t in ax.texts] == [f"run-{i}" for i in range(10)] and not fig.texts  # named in place
    plt.close(fig)


def test_gpu_fits_from_before_their_presets_recipes_are_marked_stale():
    fast_now = {"rays_per_step": 8192, "lr": 0.04, "iterations": 1000, "images_per_step": 8, "early_stop": 0.0}
    fast_before = {"rays_per_step": 4096, "lr": 0.03, "iterations": 2000, "images_per_step": 8, "early_stop": 0.0}
    paper_now = {"rays_per_step": 32768, "lr": 0.03, "iterations": 2000, "images_per_step": 8, "early_stop": 0.0}
    cpu = [{"label": "preset-paper", "psnr": 31.0, **paper_now},
           {"label": "preset-paper-all-images", "psnr": 30.0, **paper_now, "images_per_step": 0},
           {"label": "preset-fast", "psnr": 30.6, **fast_now}, {"label": "preset-fast-seed1", "psnr": 30.8, **fast_now},
           {"label": "preset-fast-4096-rays", "psnr": 30.65, **fast_before},
           {"label": "preset-fast-4096-rays-all-images-early-stop", "psnr": 30.5, **fast_before, "images_per_step": 0,
            "early_stop": 1e-4}]
    # another recipe sharing these five knobs (the authors' at 160³): not the preset's variant
    cpu.insert(0, {"label": "authors-recipe", "psnr": 29.0, **fast_before, "images_per_step": 0, "early_stop": 1e-4})
    # Rows from before the fits recorded their recipes (the paper's without even its iterations).
    fast = {"kind": "reconstruction", "preset": "fast", "psnr": 29.5, "iterations": 2000}
    paper = {"kind": "reconstruction", "preset": "paper", "psnr": 29.5, "images_per_step": 8}
    blank, fast_note, blank2, paper_note = report._stale_gpu_fits([fast, paper], cpu)
    assert blank == blank2 == ""
    assert fast_note.startswith("The GPU's `fast` run (29.50 dB) ran 2,000 steps of 4,096 rays at lr 0.03 from every "
                                "image, with the early-stop pass: the preset is now 1,000 steps of 8,192 rays at lr "
                                "0.04 from 8 images, no early-stop pass, so it is rerun")
    assert fast_note.endswith("On the CPU: 30.70 dB with 1,000 steps of 8,192 rays at lr 0.04 from 8 images, no "
                              "early-stop pass (`preset-fast`, 2 seeds); 30.50 dB with 2,000 steps of 4,096 rays at lr "
                              "0.03 from every image, with the early-stop pass "
                              "(`preset-fast-4096-rays-all-images-early-stop`, 1 seed).")
    assert "ran 2,000 steps of 32,768 rays at lr 0.03 from 8 images, with the early-stop pass" in paper_note
    # No CPU rows ran that: the nearest named, from every image without the pass.
    assert "30.00 dB with 2,000 steps of 32,768 rays at lr 0.03 from every image, no early-stop pass" in paper_note
    # A fit that ran a recipe the CPU has rows of is set beside those rows.
    (_, recorded) = report._stale_gpu_fits([{**fast, **fast_before}], cpu)
    assert recorded.endswith("30.65 dB with 2,000 steps of 4,096 rays at lr 0.03 from 8 images, no early-stop pass "
                             "(`preset-fast-4096-rays`, 1 seed).")
    recent = [{**fast, **fast_now}, {**paper, **paper_now}]
    assert report._stale_gpu_fits(recent, cpu) == [] and report._stale_gpu_fits([], cpu) == []
    assert report._stale_gpu_fits([fast], cpu[:2]) == []  # no CPU rows of the fast preset to judge it by


def test_report_docstring_examples_hold():
    import doctest

    result = doctest.testmod(report, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 3 and result.failed == 0  # place_labels, pareto_front, seed_means, ...


def test_write_results_writes_runs_and_summary_and_their_plot(tmp_path, monkeypatch, capsys):
    """bench/fit_costs.py's and bench/capture_presets.py's records, written again from their own runs: the same JSON."""
    import capture_presets
    import fit_costs

    monkeypatch.setattr(report, "RESULTS", tmp_path)
    for module, stem in ((fit_costs, "fit_costs"), (capture_presets, "capture_presets")):
        record = json.loads((report.HERE / "results" / f"{stem}.json").read_text())
        report.write_results(stem, record["runs"], module.summary(record["runs"]), module.plot)
        assert json.loads((tmp_path / f"{stem}.json").read_text()) == record
        assert (tmp_path / f"{stem}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert json.loads(capsys.readouterr().out) == record["summary"]


def test_each_device_has_its_own_pareto_front_and_a_stale_gpu_fit_is_on_none():
    cpu = [{"label": f"cpu{i}", "seconds": s, "psnr": p} for i, (s, p) in enumerate([(10, 30.0), (20, 31.0), (30, 30.5)])]
    gpu = [{"label": f"gpu{i}", "device": "cuda", "seconds": s, "psnr": p}
           for i, (s, p) in enumerate([(5, 29.0), (8, 31.5)])]
    stale = {"label": "stale", "device": "cuda:0", "seconds": 1, "psnr": 32.0, "stale": True}
    fronts = report.pareto_fronts(cpu + gpu + [stale], "seconds", "psnr")
    # GPU runs faster and better than every CPU run take none of the CPU's front, nor a stale one the GPU's
    assert [r["label"] for r in fronts["cpu"]] == ["cpu0", "cpu1"]
    assert [r["label"] for r in fronts["cuda"]] == ["gpu0", "gpu1"]
    # the reconstruction plot marks a GPU preset fit whose preset's recipe has changed since
    fast_now = {"rays_per_step": 8192, "lr": 0.04, "iterations": 1000, "images_per_step": 8, "early_stop": 0.0}
    old_fit = {"kind": "reconstruction", "preset": "fast", "device": "cuda", "psnr": 30.0, "iterations": 2000}
    ((preset, run, _, _),) = report.stale_gpu_runs([old_fit], [{"label": "preset-fast", "psnr": 30.6, **fast_now}])
    assert preset == "fast" and run is old_fit
    assert report._reconstruction_label({**old_fit, "stale": True}).endswith("(2000 it, GPU, stale recipe)")


def _readme_rows(heading: str) -> list[list[str]]:
    """The cells (bold marks dropped) of the first table under ``heading`` in bench/README.md, header row left out."""
    text = (report.HERE / "README.md").read_text().split(f"\n{heading}\n", 1)[1]
    rows = []
    for line in text.split("\n| ", 1)[1].split("\n\n", 1)[0].splitlines()[2:]:
        rows.append([cell.strip().strip("*").strip() for cell in line.strip().strip("|").split("|")])
    return rows


def test_bench_readmes_tables_hold_the_json_rounded_as_report_rounds_it():
    reconstruction = {r["label"]: r for r in json.loads((report.RESULTS / "reconstruction.json").read_text())}
    for label, *cells in _readme_rows("## Reconstruction: latest table"):
        run = reconstruction[label]
        assert [cells[5], cells[6], cells[10], cells[11]] == [report.fmt(float(run["psnr"])),
                                                              report.fmt(float(run["ssim"]), 4),
                                                              report.fmt(float(run["peak_rss_mb"]), 0),
                                                              run["commit"]], label
    priors = json.loads((report.RESULTS / "real_scenes_priors.json").read_text())
    rows = _readme_rows("## Real scenes: priors for a capture's few views (`real_scenes_priors.py`, "
                        "results/real_scenes_priors.json)")
    assert len(rows) == len(priors)
    for variant, *_, validation, held_out, fitting in rows:
        run = priors[variant.split()[0]]
        assert [validation, held_out, fitting] == [report.fmt(float(run["validation"]["psnr"])),
                                                   report.fmt(float(run["held_out"]["psnr"])),
                                                   report.fmt(float(run["fitting_views_psnr"]))], variant


def test_every_reconstruction_row_records_the_recipe_its_label_reruns_with():
    """`bench/reconstruction.py --only LABEL` reruns what the row measured: its early-stop pass (rows from before
    90eb259 ran it, then every object fit's default), its draw, its step."""
    import reconstruction

    from voxe_core.reconstruct import ReconstructConfig

    fast = ReconstructConfig.fast()
    defaults = {"early_stop": fast.render.early_stop, "images_per_step": fast.images_per_step,
                "rays_per_step": fast.rays_per_step, "lr": fast.lr}
    recipes = {label: overrides for label, *_, overrides in reconstruction.FULL_RUNS + reconstruction.ABLATION_RUNS}
    for row in json.loads((report.RESULTS / "reconstruction.json").read_text()):
        overrides = recipes[row["label"].removesuffix("-box")]  # a box row: its label's run with --resample box
        assert {key: row.get(key) for key in defaults} == {key: overrides.get(key, value)
                                                           for key, value in defaults.items()}, row["label"]


def test_iteration_budget_bullets_name_each_runs_commit_where_the_rows_come_from_different_runs():
    def row(label, iterations, commit, bench_run):
        return {"label": label, "resolution": 128, "rays_per_step": 4096, "skipping": True, "iterations": iterations,
                "psnr": 30.0, "seconds": 20.0, "commit": commit, "bench_run": bench_run}

    one_run = [row("short", 1000, "abc1234", "r1"), row("long", 2000, "abc1234", "r1")]
    (bullet,) = [b for b in report.reconstruction_tradeoffs(one_run) if "Iteration budget" in b]
    assert "different runs" not in bullet and "(at " not in bullet
    (bullet,) = [b for b in report.reconstruction_tradeoffs(one_run[:1] + [row("long", 2000, "def5678", "r2")])
                 if "Iteration budget" in b]
    assert bullet.startswith("**Iteration budget** (reconstruction at 128³, 4,096 rays a step, seed 0; measured in "
                             "different runs, each at its commit: not ratios of one run)")
    assert "short 1000 it → 30.0 dB in 20.0 s (at abc1234), long 2000 it → 30.0 dB in 20.0 s (at def5678)" in bullet
    pair = [{**r, "label": label} for r, label in zip(one_run[:1] + [row("x", 2000, "def5678", "r2")],
                                                       ("recipe-4096-rays", "recipe"))]
    (twins,) = report.recipe_twin_tradeoffs(pair)
    assert "measured in different runs, at abc1234 and def5678: seconds not compared" in twins


def test_a_quick_edit_step_run_keeps_the_full_size_record(tmp_path, monkeypatch):
    """`bench/edit_step.py --quick` writes under results/quick/ (as `report.py --quick`), or to --out."""
    import edit_step

    row = {"model": "tiny", "device": "cpu", "dtype": "float32", "resolution": 64, "render_size": 64,
           "edit_8000_minutes": 1.0, **{f"ms_{part}": 1.0 for part in edit_step.PARTS}, "ms_total": 6.0}
    monkeypatch.setattr(edit_step, "RESULTS", tmp_path)
    monkeypatch.setattr(edit_step, "time_run", lambda *args: row)
    monkeypatch.setattr(edit_step.torch, "set_num_threads", lambda n: None)
    edit_step.main(["--quick"])
    assert json.loads((tmp_path / "quick" / "edit_step.json").read_text()) == [row]
    assert (tmp_path / "quick" / "edit_step.png").is_file() and not (tmp_path / "edit_step.json").exists()
    edit_step.main(["--quick", "--out", str(tmp_path / "elsewhere.json")])
    assert (tmp_path / "elsewhere.png").is_file()
    assert edit_step.default_out(False, True) == tmp_path / "edit_step_gpu.json"


def test_fit_costs_answers_help_and_refuses_unknown_arguments_without_fitting(monkeypatch, capsys):
    import fit_costs

    monkeypatch.setattr(fit_costs, "fit", lambda *args: pytest.fail("a fit started"))
    with pytest.raises(SystemExit) as done:
        fit_costs.main(["--help"])
    assert done.value.code == 0 and "bench/fit_costs.py" in capsys.readouterr().out
    with pytest.raises(SystemExit) as done:
        fit_costs.main(["--preset", "paper"])
    assert done.value.code == 2


def test_time_axes_are_logarithmic_and_small_seconds_keep_their_digits(tmp_path, monkeypatch):
    figures = []
    monkeypatch.setattr(report, "figure_link", lambda fig, *args, **kwargs: figures.append(fig) or [])
    edit = [{"model": "tiny", "device": "cpu", "dtype": "float32", "resolution": 64, "ms_render": 10.0,
             "ms_unet": 2.0, "ms_total": 30.0}]
    report.edit_step_section(edit, [], tmp_path, tmp_path / "REPORT.md")
    parts, total = figures[-1].axes
    assert parts.get_xscale() == total.get_xscale() == "log"
    assert "\n" in total.get_title()  # wrapped: the panel's title ran off the figure
    phase = {"requests": 10, "p50_ms": 5.0, "p90_ms": 9.0, "p99_ms": 300.0, "errors": 0}
    report.service_load_section({"status": phase, "targets": {"status_p99_ms": 25.0}}, tmp_path, tmp_path / "R.md")
    assert figures[-1].axes[0].get_yscale() == "log"
    summary = [{"method": m, "scene": "any", "noise": 0.2, "iou_mean": 0.8, "iou_min": 0.7}
               for m in ("vote_2d", "threshold_3d")]
    runs = [{"method": "vote_2d", "scene": "any", "seconds": 0.0468, "iou": 0.8},
            {"method": "threshold_3d", "scene": "any", "seconds": 12.677, "iou": 0.8}]
    lines, _ = report.segmentation_section({"summary": summary, "runs": runs}, tmp_path, tmp_path / "R.md")
    assert "| vote_2d | any | 0.800 (0.700) | 0.0468 |" in lines and "| threshold_3d | any | 0.800 (0.700) | 12.7 |" in lines
    for fig in figures:
        report._pyplot().close(fig)


def test_service_load_meets_its_targets_only_at_their_load():
    from argparse import Namespace

    import service_load

    phase = {"p99_ms": 10.0, "errors": 0}
    result = {"status": phase, "status_during_submit": phase, "submit": {**phase, "accepted": 100}, "lost_jobs": 0,
              "streams": {"open_during_status": 50, "errors": 0}}
    quick = service_load.judge_targets(result, Namespace(pollers=10, jobs=100, streams=50))
    assert quick["targets_met"] is None and quick["targets"]["submissions"] == 100 and quick["targets"]["pollers"] == 10
    assert quick["targets_note"] == "not at target size (pollers 10 of 50, jobs 100 of 1000); at this load the checks passed"
    full = {**result, "submit": {**phase, "accepted": 1000}}
    assert service_load.judge_targets(full, Namespace(pollers=50, jobs=1000, streams=50))["targets_met"] is True
    lost = {**full, "lost_jobs": 1}
    judged = service_load.judge_targets(lost, Namespace(pollers=50, jobs=1000, streams=50))
    assert judged["targets_met"] is False and "targets_note" not in judged


@needs_data(MIC, DATA_ROOT / "meshes" / "horse")
def test_object_fits_of_records_from_before_2026_12_05_rerun_the_recipe_they_measured(monkeypatch, tmp_path):
    """grid_files.py, mesh_input.py and localisation_grids.py fit objects with fast() as their records measured it:
    every image's rays each step and the early-stop pass (fast() has drawn from 8 images and gone without the pass
    since 2026-12-05; the three had pinned only its earlier step)."""
    from argparse import Namespace

    import grid_files
    import localisation_grids
    import mesh_input

    import voxe_core.reconstruct
    from voxe_core.cameras import Cameras, ring_poses

    class Fitted(Exception):
        pass

    configs = []

    def record(images, cameras, config, *args, **kwargs):
        configs.append(config)
        raise Fitted

    monkeypatch.setattr(voxe_core.reconstruct, "reconstruct", record)
    cameras = Cameras.from_fov(ring_poses(2, 30.0), 0.69, 8, 8)
    with pytest.raises(Fitted):
        localisation_grids.fit(torch.ones(2, 8, 8, 3), cameras, 8, tmp_path / "grid.safetensors")
    with pytest.raises(Fitted):
        mesh_input.run_mesh("horse", Namespace(views=2, size=8, test_views=1, resolution=8, voxelize_resolution=8,
                                               iterations=(1, 1), rays=64))
    with pytest.raises(Fitted):
        grid_files.scene_grids(Namespace(only=["mic"], quick=True, resolution=12))
    assert [(c.images_per_step, c.render.early_stop, c.lr) for c in configs] == [(0, 1e-4, 0.03)] * 3
