"""``bench/bench_gpu_scale.py --render-compare`` keeps working here: on a cheap gym scene it runs
one pinned pod with the machine's default EGL and one with Mesa's chosen through its glvnd vendor
file, the same open-loop actions from the same init states, and prints one ``RESULT {json}``
line with each renderer's GL strings and libraries, the time split and the pixel comparison.

Here both renderers are Mesa's llvmpipe (this machine has no GPU), so the two pods must see the
same states and draw the same bytes. Run as a person would run it, from a copy of ``bench/`` in a
temporary directory. No timing is asserted.
"""

from __future__ import annotations

import glob
from pathlib import Path
from typing import Any

import pytest
from support.bench_scripts import bench_env, bench_result

# slow: a benchmark script run end to end, with its own pods (20-30 s on 2 cores).
pytestmark = [
    pytest.mark.skipif(
        not glob.glob("/usr/share/glvnd/egl_vendor.d/*mesa*.json"), reason="needs the machine's Mesa EGL vendor file"
    ),
    pytest.mark.slow,
]


@pytest.fixture(scope="module")
def result(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    root = tmp_path_factory.mktemp("render-compare")
    # EGL whatever the caller's shell says, and none of the caller's Mesa choices.
    env = bench_env(
        drop=("VECSIM_TOKEN", "VECSIM_MESA_EGL_VENDOR", "VECSIM_MESA_LIBRARY_PATH", "VECSIM_MESA_DRIVERS"),
        extra={"MUJOCO_GL": "egl"},
    )
    summary = bench_result(
        root,
        "bench_gpu_scale.py",
        "--render-compare",
        "--tasks",
        "gym/HalfCheetah-v5",
        "--size",
        "16",
        "--envs-per-task",
        "2",
        "--horizon",
        "3",
        "--rounds",
        "1",
        timeout=170,
        env=env,
    )
    return summary, root


@pytest.mark.timeout(180)
def test_each_renderer_reports_its_gl_strings_and_egl_libraries(result):
    summary, _ = result
    assert summary["name"] == "bench_gpu_render_compare_cpu" and summary["gpu_is_nvidia"] is False
    for run in summary["renderers"].values():
        assert run["gl"]["backend"] == "egl" and run["gl"]["vendor"] and run["gl"]["renderer"]
        assert any("EGL" in Path(path).name for path in run["gl"]["libraries"]), run["gl"]["libraries"]
    software = summary["renderers"]["software"]
    assert "llvmpipe" in software["gl"]["renderer"]
    assert software["env"]["__EGL_VENDOR_LIBRARY_FILENAMES"].endswith(".json")


@pytest.mark.timeout(180)
def test_both_pods_are_measured_with_physics_and_render_time(result):
    summary, _ = result
    for run in summary["renderers"].values():
        assert run["env_steps_per_s"]["median"] > 0
        assert run["time_split_ms"]["physics_ms_per_env_step"] > 0
        assert run["time_split_ms"]["render_ms_per_env_step"] > 0
    assert summary["ratio"] > 0 and summary["setup"]["pod_pinned_to"]


@pytest.mark.timeout(180)
def test_the_same_renderer_twice_sees_the_same_states_and_draws_the_same_bytes(result):
    summary, _ = result
    images = summary["images"]
    assert images["same_states"] is True and images["steps_compared"] == 4 and images["trajectories"] == 2
    assert images["cameras"]["render"]["identical"] is True
    assert images["cameras"]["render"]["mean_abs_diff"] == 0


@pytest.mark.timeout(180)
def test_the_bar_chart_and_the_frames_figure_are_written(result):
    summary, root = result
    assert {Path(p).name for p in summary["plots"]} == {
        "gpu_render_compare_cpu.png",
        "gpu_render_compare_cpu_frames.png",
    }
    assert all((root / p).is_file() for p in summary["plots"])
    assert (root / "out" / "bench" / "bench_gpu_render_compare_cpu.json").is_file()
