"""LIBERO against vecsim, frame by frame: what each shows after a reset or a step (images, joints,
end-effector, state, MuJoCo state) and their largest differences. Shared by the parity sweeps
(``libero_parity_sweep.py``, ``libero_published_sweep.py``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

CAMERAS = ("agentview", "robot0_eye_in_hand")
SETTLE_STEPS = 10
NO_OP = [0.0] * 6 + [-1.0]
# robot0_joint_pos_cos (7), robot0_joint_pos_sin (7), robot0_eef_pos (3) at the head of proprio.
_COS, _SIN, _EEF = slice(0, 7), slice(7, 14), slice(14, 17)


def axis_angle(quat: np.ndarray) -> np.ndarray:
    """robosuite's ``quat2axisangle`` of an ``(x, y, z, w)`` quaternion, as LIBERO's evaluations use it."""
    w = min(max(float(quat[3]), -1.0), 1.0)
    den = math.sqrt(1.0 - w * w)
    if math.isclose(den, 0.0):
        return np.zeros(3)
    return np.asarray(quat[:3], dtype=np.float64) * 2.0 * math.acos(w) / den


def libero_frame(env: Any, raw: dict[str, np.ndarray]) -> dict[str, Any]:
    """What LIBERO's own env shows after a step, as :func:`vecsim_frame` reads vecsim's."""
    return {
        "images": {name: raw[f"{name}_image"][::-1, ::-1].copy() for name in CAMERAS},
        # As vecsim's float32 proprio carries them, so equal sims give equal numbers.
        "joints": np.arctan2(
            raw["robot0_joint_pos_sin"].astype(np.float32).astype(np.float64),
            raw["robot0_joint_pos_cos"].astype(np.float32).astype(np.float64),
        ),
        "eef": raw["robot0_eef_pos"].astype(np.float32).astype(np.float64),
        "state": np.concatenate(
            [raw["robot0_eef_pos"], axis_angle(raw["robot0_eef_quat"]), raw["robot0_gripper_qpos"]]
        ).astype(np.float32),
        "sim": env.get_sim_state().copy(),
    }


def vecsim_frame(env: Any, obs: dict[str, Any]) -> dict[str, Any]:
    """The same figures of a vecsim env's observation."""
    proprio = obs["proprio"].astype(np.float64)
    return {
        "images": {name: obs["images"][name] for name in CAMERAS},
        "joints": np.arctan2(proprio[_SIN], proprio[_COS]),
        "eef": proprio[_EEF],
        "state": obs.get("state"),
        "sim": env.inner.sim.get_state().flatten(),
    }


def differences(theirs: dict[str, Any], ours: dict[str, Any]) -> dict[str, float | None]:
    """Largest absolute differences: pixels per camera, joints (mrad), eef (mm), state, sim state."""
    found: dict[str, float | None] = {
        f"{name}_px": float(np.abs(theirs["images"][name].astype(np.int16) - ours["images"][name]).max())
        for name in CAMERAS
    }
    found["joints_mrad"] = float(np.abs(theirs["joints"] - ours["joints"]).max() * 1e3)
    found["eef_mm"] = float(np.abs(theirs["eef"] - ours["eef"]).max() * 1e3)
    found["state"] = None if ours["state"] is None else float(np.abs(theirs["state"] - ours["state"]).max())
    found["sim_state"] = float(np.abs(theirs["sim"] - ours["sim"]).max())
    return found


def worst(rows: list[dict[str, float | None]]) -> dict[str, float | None]:
    return {key: None if rows[0][key] is None else max(row[key] for row in rows) for key in rows[0]}


def exact(found: dict[str, float | None]) -> bool:
    return all(value in (0.0, None) for value in found.values())
