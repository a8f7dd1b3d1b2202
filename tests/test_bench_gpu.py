"""bench/gpu.py, the prepared GPU benchmark, runs end to end (its CPU --smoke profile: tiny sizes, the
random-weight SMOKE-TEST model; the figures mean nothing, the test checks the record's shape)."""

from __future__ import annotations

import dataclasses
import gc
import importlib.util
import json
import os
import signal
import sys
import time
import weakref
from pathlib import Path

import pytest
import torch

from needs import MIC, require_data, require_triton_interpreter

pytestmark = pytest.mark.slow
BENCH = Path(__file__).resolve().parents[1] / "bench" / "gpu.py"


def _load_bench(monkeypatch):
    """bench/gpu.py as a module (registered in sys.modules: its dataclasses look their module up there)."""
    spec = importlib.util.spec_from_file_location("bench_gpu", BENCH)
    bench = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "bench_gpu", bench)
    spec.loader.exec_module(bench)
    return bench


def test_gpu_bench_smoke_run_writes_every_section(tmp_path, monkeypatch):
    require_data(MIC)
    bench = _load_bench(monkeypatch)
    out, earlier = tmp_path / "gpu.json", tmp_path / "earlier.json"
    earlier_loop = {"name": "edit_loop, CUDA graphs", "kind": "edit", "section": "g", "call": 6, "device": "cuda",
                    "ms_step": 1000.0}  # an earlier call's loop beside another model: no projection reads it
    earlier.write_text(json.dumps({"calls": {"6": "g"}, "runs": [earlier_loop]}))
    assert bench.main(["--smoke", "--out", str(out), "--call", "7", "--call-note", "the smoke run", "--skip", "g,l",
                       "--keep", str(earlier)]) == 0
    record = json.loads(out.read_text())
    assert record["runs"][0] == {**earlier_loop, "kept_from_earlier_call": True}
    runs = record["runs"][1:]
    assert not [r for r in runs if "error" in r]
    kinds = [r["kind"] for r in runs]
    assert kinds == ["edit_step"] * len(bench.STEP_VARIANTS) + ["edit"] + ["reconstruction"] * 4 + ["refinement"] + ["render_passes"] * 8 \
        + ["interpolation"] * 6 + ["edit_step"] * 3 + ["step_profile", "job"]  # i: the CPU's default pass size, 2^23, no early stop
    assert record["calls"] == {"6": "g", "7": "the smoke run"} and {r["call"] for r in runs} == {7}
    for run in runs:
        assert {"name", "device", "dtype", "model", "peak_memory_gb"} <= set(run)
        assert run["device"] == "cpu" and run["peak_memory_gb"] > 0
    for run in runs[: len(bench.STEP_VARIANTS) + 1]:
        assert run["ms_step"] > 0 and run["edit_8000_minutes"] == pytest.approx(run["ms_step"] * 8000 / 60000)
    assert runs[0]["speedup_over_baseline"] == 1.0
    for run in runs[: len(bench.STEP_VARIANTS)]:  # each variant's accuracy against the baseline, same run (here fp32)
        assert run["sds_grad_relative_difference"] == 0 and run["encoder_image_grad_relative_difference"] == 0
    assert all(r["ms_render"] > 0 and r["ms_unet"] > 0 for r in runs[:4])  # synchronised variants split the step
    for run in runs:
        if run["kind"] == "reconstruction":
            assert run["seconds"] > 0 and 5 < run["psnr"] < 60 and 0 < run["ssim"] <= 1
            assert run["images_per_step"] == 8  # what the row was fitted with: both presets draw from 8 images
    fast, probing, smaller, paper = (r for r in runs if r["kind"] == "reconstruction")  # fast, then its variants
    assert (fast["preset"], probing["preset"], smaller["preset"], paper["preset"]) == ("fast", "fast", "fast", "paper")
    assert (fast["early_stop"], probing["early_stop"], probing["variant"]) == (0.0, 1e-4, "the early-stop pass")
    assert probing["seconds_over_default"] == pytest.approx(probing["seconds"] / fast["seconds"])
    assert smaller["variant"] == "twice the steps of half the rays at lr 0.03" and smaller["early_stop"] == 0.0
    assert (smaller["rays_per_step"] * 2, smaller["iterations"], smaller["lr"]) == \
        (fast["rays_per_step"], 2 * fast["iterations"], 0.03)
    assert smaller["seconds_over_default"] == pytest.approx(smaller["seconds"] / fast["seconds"])
    refinement = next(r for r in runs if r["kind"] == "refinement")  # the split: maps, then the lift and the cut
    assert refinement["seconds_attention_maps"] + refinement["seconds_grids_and_cut"] == \
        pytest.approx(refinement["seconds"])
    assert 0 < refinement["seconds_backprojection"] <= refinement["seconds_grids_and_cut"]
    passes = [r for r in runs if r["kind"] == "render_passes"]
    for scene in ("sphere", "fog"):  # grouping never moves the render; larger passes never dispatch more
        mine = [r for r in passes if r["scene"] == scene]
        assert [r["samples_per_pass"] for r in mine] == sorted(r["samples_per_pass"] for r in mine)
        assert all(r["max_rgb_difference"] == 0 and r["max_gradient_difference"] < 1e-5 for r in mine)
        assert [r["operations"] for r in mine] == sorted((r["operations"] for r in mine), reverse=True)
    variants = [r for r in runs if r["kind"] == "interpolation"]  # on the CPU every variant adds in index order
    assert [(r["scene"], r["variant"]) for r in variants] == [
        (scene, variant) for scene in ("sphere", "fog") for variant in ("default", "embedding backward",
                                                                        "mul-sum forward")]
    assert all(r["max_gradient_difference"] == 0 and r["backward_ms"] > 0 for r in variants)
    assert all(r["max_rgb_difference"] == 0 for r in variants if r["variant"] != "mul-sum forward")
    default_passes, large_passes, no_early_stop = (r for r in runs if r["section"] == "i")
    assert (default_passes["samples_per_pass"], large_passes["samples_per_pass"]) == (1 << 20, 1 << 23)
    assert (default_passes["early_stop"], no_early_stop["early_stop"], no_early_stop["samples_per_pass"]) == (
        1e-4, 0.0, 1 << 20)
    assert default_passes["speedup_over_2_20"] == 1.0
    for run in (default_passes, large_passes, no_early_stop):  # the backward split where the gradient reaches the renders
        assert run["ms_backward_guidance"] > 0 and run["ms_backward_render"] > 0
        assert run["ms_backward_guidance"] + run["ms_backward_render"] == pytest.approx(run["ms_backward"])
    profiled = next(r for r in runs if r["kind"] == "step_profile")  # on the CPU: host operations only
    assert profiled["profiled_ms_step"] > 0 and profiled["device_busy_ms_per_step"] is None
    assert profiled["kernel_launches_per_step"] == 0 and profiled["aten_calls_per_step"] > 100
    host = profiled["top_host_operations"]
    assert host and all(e["name"].startswith("aten::") and e["calls_per_step"] > 0 for e in host)
    assert [e["ms_per_step"] for e in host] == sorted((e["ms_per_step"] for e in host), reverse=True)
    job = next(r for r in runs if r["kind"] == "job")
    assert job["state"] == "succeeded"
    loop = next(r for r in runs if r["section"] == "b")  # projected with the default loop's step
    assert job["seconds_projected_8000_iterations"] == pytest.approx(
        job["seconds"] + (8000 - job["edit_iterations"]) * loop["ms_step"] / 1e3)
    assert set(job["peak_memory_gb_per_stage"]) == {"reconstruct", "edit", "refine", "export"}
    assert (tmp_path / "gpu.png").stat().st_size > 1000


def test_a_call_cut_off_by_its_time_limit_keeps_what_it_measured(tmp_path, monkeypatch):
    """SIGTERM (bench/gpu_device.sh's `timeout`) in the middle of the job: its row says so and keeps the stages done
    by then; a cut in an earlier section leaves the later ones unstarted; the handler is put back afterwards."""
    require_data(MIC)
    bench = _load_bench(monkeypatch)

    def cut_off_job(*args):
        args[-1]["seconds_per_stage"] = {"reconstruct": 26.1}  # what the job had done
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(30)  # the handler raises here
        raise AssertionError("not reached")

    monkeypatch.setattr(bench, "job_run", cut_off_job)
    before = signal.getsignal(signal.SIGTERM)
    out = tmp_path / "job.json"
    assert bench.main(["--smoke", "--out", str(out), "--skip", "a,b,c,d,h,i,l,k"]) == 1
    (run,) = json.loads(out.read_text())["runs"]
    assert run["section"] == "f" and run["error"] == "CallTimeLimit: terminated by the call's time limit (SIGTERM)"
    assert run["seconds_per_stage"] == {"reconstruct": 26.1} and run["seconds"] < 30
    assert signal.getsignal(signal.SIGTERM) is before

    def cut_off_render_passes(*args):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(30)

    monkeypatch.setattr(bench, "render_pass_runs", cut_off_render_passes)
    monkeypatch.setattr(bench, "job_run", lambda *args: pytest.fail("a section after the cut started"))
    out = tmp_path / "render.json"
    assert bench.main(["--smoke", "--out", str(out), "--skip", "a,b,c,d"]) == 1
    assert [r["section"] for r in json.loads(out.read_text())["runs"]] == ["h"]


def _interpreted_bench(monkeypatch):
    """bench/gpu.py and a profile small enough for Triton's interpreter (8² renders, a 12³ grid, one loop iteration)."""
    require_triton_interpreter()
    bench = _load_bench(monkeypatch)
    return bench, dataclasses.replace(bench.Profile.smoke(), render_size=8, grid_resolution=12, loop_iterations=1)


def test_section_l_sets_the_fused_marcher_against_the_packed_renderer(monkeypatch, tiny_sd_path, single_thread):
    """Section l on this CPU (the smoke run leaves it out: Triton's interpreter takes ~60 s at its sizes), smaller
    still: the fused render and gradient agree with the packed ones, evaluate fewer samples, and the steps are timed
    (figures that mean nothing here); each row says whether the fused path ran."""
    bench, profile = _interpreted_bench(monkeypatch)
    rows = bench.fused_marcher_runs(tiny_sd_path, profile)
    renders = [r for r in rows if r["kind"] == "fused_render"]
    assert [(r["scene"], r["marcher"]) for r in renders] == [
        (scene, marcher) for scene in ("sphere", "fog") for marcher in ("packed", "fused")]
    for packed, fused in zip(renders[::2], renders[1::2]):
        assert (packed["marched_fused"], fused["marched_fused"]) == (False, True)
        assert fused["max_rgb_difference"] < 1e-5 and fused["max_gradient_difference"] < 1e-4
        assert 0 < fused["samples"] <= packed["samples"]
        assert fused["ms_ratio_to_reference"] == pytest.approx(fused["ms"] / packed["ms"])
    packed_step, fused_step = rows[4:]
    assert (packed_step["speedup_over_packed"], packed_step["name"]) == (1.0, "edit_step packed marcher (the default)")
    assert (packed_step["fused_marcher"], fused_step["fused_marcher"]) == (False, True)
    assert fused_step["speedup_over_packed"] == pytest.approx(packed_step["ms_step"] / fused_step["ms_step"])
    assert fused_step["ms_render"] > 0 and fused_step["samples_per_ray"] < packed_step["samples_per_ray"]


def test_the_edit_loop_runs_with_the_fused_marcher_when_asked(monkeypatch, tiny_sd_path, single_thread):
    """``--fused-marcher`` (``Profile.fused_marcher``): section b's loop renders through the fused marcher (which
    evaluates each kept sample once, the packed path probes them all first) and its row says so."""
    bench, small = _interpreted_bench(monkeypatch)
    packed, fused = (bench.edit_loop_run(tiny_sd_path, dataclasses.replace(small, fused_marcher=flag))
                     for flag in (False, True))
    assert (packed["fused_marcher"], fused["fused_marcher"]) == (False, True)
    assert fused["name"] == "edit_loop 1 iterations at 12³, fused marcher" and "fused" not in packed["name"]
    assert 0 < fused["samples_per_ray"] < packed["samples_per_ray"]


def test_section_a_computes_the_agreement_outputs_once_per_state_of_the_guidance(monkeypatch, tiny_sd_path,
                                                                                 single_thread):
    """Fused Adam and the timing sync leave the guidance as it was: their variants compare the outputs of the one
    before (each variant had computed them again). On the CPU every variant runs one fp32 guidance, laid out as
    loaded: one computation for the five rows, each row still with its agreement."""
    bench = _load_bench(monkeypatch)
    profile = dataclasses.replace(bench.Profile.smoke(), render_size=8, grid_resolution=12)
    computed, real_outputs = [], bench._agreement_outputs

    def counted_outputs(guidance, profile):
        computed.append(guidance)
        return real_outputs(guidance, profile)

    monkeypatch.setattr(bench, "_agreement_outputs", counted_outputs)
    rows = bench.edit_step_runs(tiny_sd_path, profile)
    assert len(rows) == len(bench.STEP_VARIANTS) and len(computed) == 1
    for row in rows:
        assert row["sds_grad_relative_difference"] == row["encoder_latents_relative_difference"] == \
            row["encoder_image_grad_relative_difference"] == 0


def test_section_g_sets_its_steps_against_section_as_baseline_only_from_the_same_call(monkeypatch):
    bench = _load_bench(monkeypatch)
    baseline = {"name": "edit_step baseline", "section": "a", "ms_step": 120.0}
    later = {"name": "edit_step + fp16", "section": "a", "ms_step": 100.0}
    assert bench._same_call_baseline([baseline, later]) == 120.0
    # kept from an earlier call (--keep): another process, another state of the machine, no ratio
    assert bench._same_call_baseline([{**baseline, "kept_from_earlier_call": True}]) is None
    assert bench._same_call_baseline([{"section": "a", "error": "x"}]) is None
    kept = json.loads((BENCH.parent / "results" / "gpu.json").read_text())["runs"]
    assert all("speedup_over_baseline" not in r for r in kept if r.get("section") == "g")  # call 2 against call 1


def test_sections_g_and_j_measure_each_variant_with_only_its_own_model_loaded(tmp_path, monkeypatch):
    """Each step's peak memory is its own model's: no other guidance is alive while a variant runs (on the CPU, with
    the graphs and the compile off: what is measured here is which models are loaded, not their speed)."""
    from voxe_core.tiny_sd import build_tiny_stable_diffusion

    bench = _load_bench(monkeypatch)
    profile = bench.Profile.smoke()
    tiny = build_tiny_stable_diffusion(tmp_path / "tiny", seed=0)
    loaded, alive_while_measured = [], []
    real_guidance, real_edit_run = bench._guidance, bench._edit_run

    def cpu_guidance(path, profile, dtype, cuda_graphs=None, compile_encoder=None):
        guidance = real_guidance(path, profile, dtype, cuda_graphs=False, compile_encoder=False)
        loaded.append(weakref.ref(guidance))
        return guidance

    def counting_edit_run(*args, **kwargs):
        gc.collect()
        alive_while_measured.append(sum(ref() is not None for ref in loaded))
        return real_edit_run(*args, **kwargs)

    monkeypatch.setattr(bench, "_guidance", cpu_guidance)
    monkeypatch.setattr(bench, "_edit_run", counting_edit_run)
    monkeypatch.setattr(bench, "ENCODER_VARIANTS", bench.ENCODER_VARIANTS[:2])  # the third graphs, CUDA only
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # toy-sized ops, as the smoke run
    try:
        eager, graphed, loop, diagnostic = bench.cuda_graph_runs(tiny, profile, None)
        encoders = bench.compiled_encoder_runs(tiny, profile)
    finally:
        torch.set_num_threads(threads)
    assert len(loaded) == 5 and alive_while_measured and set(alive_while_measured) == {1}
    assert not [r for r in encoders if "error" in r]
    assert graphed["sds_grad_relative_difference"] == 0 and graphed["encoder_image_grad_relative_difference"] == 0
    assert eager["speedup_over_eager"] == 1 and "speedup_over_baseline" not in eager  # no baseline of this call
    assert loop["kind"] == "edit" and diagnostic["batch_8_over_batch_2"] > 0


def test_gpu_plot_puts_time_on_log_axes_and_labels_same_call_ratios(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    bench = _load_bench(monkeypatch)
    closed = []
    monkeypatch.setattr(plt, "close", closed.append)
    runs = [{"name": "edit_step eager", "kind": "edit_step", "device": "cuda", "ms_step": 98.0, "speedup_over_eager": 1.0},
            {"name": "edit_step graphs", "kind": "edit_step", "device": "cuda", "ms_step": 84.0,
             "speedup_over_eager": 98 / 84},
            {"name": "job", "kind": "job", "device": "cuda", "seconds": 61.6}]
    bench.plot(runs, tmp_path / "gpu.png")
    (fig,) = closed
    left, right = fig.axes
    assert left.get_xscale() == right.get_xscale() == "log"
    assert [t.get_text() for t in left.texts] == ["  98 ms  ×1.00 vs eager", "  84 ms  ×1.17 vs eager"]
    assert "\n" in right.get_title()
    monkeypatch.undo()
    plt.close(fig)
