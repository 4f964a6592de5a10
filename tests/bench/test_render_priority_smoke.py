"""``bench/bench_render_priority.py --quick`` keeps working here: a CPU policy timed alone and
beside one render process a priority (a LIBERO scene, Mesa's llvmpipe), interleaved rounds, and
one ``RESULT {json}`` line with each contender's times, the ratios and the GL context each set of
renderers was granted. Mesa offers no context priorities, so both sets report ``medium``. Run as
a person would run it, from a copy of ``bench/``. No timing is asserted.
"""

from __future__ import annotations

from typing import Any

import pytest
from support.bench_scripts import bench_env, bench_result

# A LIBERO scene a renderer, a torch policy: 40-60 s on 2 cores.
pytestmark = [pytest.mark.slow, pytest.mark.libero]


@pytest.fixture(scope="module")
def summary(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    root = tmp_path_factory.mktemp("render-priority")
    env = bench_env(drop=("VECSIM_TOKEN", "VECSIM_RENDER_PRIORITY"), extra={"MUJOCO_GL": "egl"})
    return bench_result(root, "bench_render_priority.py", "--quick", "--priorities", "medium,low", timeout=280, env=env)


@pytest.mark.timeout(300)
def test_each_contender_is_timed_in_every_round(summary: dict[str, Any]) -> None:
    assert summary["name"] == "bench_render_priority"
    assert set(summary["policy_ms"]) == {"alone", "renders/medium", "renders/low"}
    assert all(spread["n"] == 2 and spread["min"] > 0 for spread in summary["policy_ms"].values())
    assert set(summary["render_ms"]) == {"renders/medium", "renders/low"}
    assert all(spread["n"] == 2 and spread["min"] > 0 for spread in summary["render_ms"].values())
    assert set(summary["policy_slowdown_over_alone"]) == {"renders/medium", "renders/low"}
    assert summary["policy_speedup_over_medium"]["renders/low"]["n"] == 2


@pytest.mark.timeout(300)
def test_each_set_of_renderers_reports_the_priority_it_was_granted(summary: dict[str, Any]) -> None:
    # llvmpipe has no EGL_IMG_context_priority: the low set renders at the default and says so.
    assert summary["granted"] == {"medium": ["medium"], "low": ["medium"]}
    assert summary["gl"]["low"]["backend"] == "egl" and summary["gl"]["low"]["renderer"]
