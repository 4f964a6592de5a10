"""One env action of a batch of worlds, as robosuite runs it, and what makes a world's step wrong.

:func:`apply_action` runs an action's physics substeps in every world of a batch (on a GPU as one
captured CUDA graph); :func:`overflow_reason` names the MuJoCo Warp overflow a world's flags
report, one that makes its trajectory wrong (its env's error, never a NaN observation).
"""

from __future__ import annotations

from typing import Any


def _action_substeps(batch: Any) -> None:
    """One env action in every world of ``batch``: its physics substeps as robosuite runs them
    (controller between ``step1`` and ``step2``); the observables and the cameras' kinematics
    where LIBERO samples them, the goal after the last substep."""
    import mujoco_warp as mjw
    import warp as wp

    from vecsim.engine.mjwarp.observables import LIBERO_SAMPLE_SUBSTEP

    data, model, controller, action = batch.data, batch.model, batch.controller, batch.action
    data.overflow.zero_()
    substeps = int(batch.scene.manifest["robot"]["substeps"])
    sample = min(LIBERO_SAMPLE_SUBSTEP, substeps - 1)
    for substep in range(substeps):
        mjw.step1(model, data)
        if substep == 0:
            controller.set_goal(action, data.site_xpos, data.site_xmat)
        controller.apply(
            action,
            data.qpos,
            data.qvel,
            data.M,
            data.qfrc_bias,
            data.site_xpos,
            data.site_xmat,
            data.xanchor,
            data.xaxis,
            data.ctrl,
        )
        mjw.step2(model, data)
        if substep == sample:
            batch.observables.compute(data.qpos, data.site_xpos, data.xquat)
            for name, view in (batch.view or {}).items():
                wp.copy(view, getattr(data, name))
    batch.goal.evaluate(
        data.qpos, data.xpos, data.site_xpos, data.site_xmat, data.nacon, data.contact.geom, data.contact.worldid
    )


def apply_action(batch: Any) -> None:
    """Run :func:`_action_substeps` on ``batch``: on a GPU as one CUDA graph, captured the first
    time (a few hundred kernel launches an action otherwise cost more than the kernels)."""
    import warp as wp

    device = batch.controller.device
    if not device.is_cuda:
        _action_substeps(batch)
        return
    if batch.graph is None:
        # The first action runs as it is, which compiles and loads every kernel it launches;
        # a capture records launches without running them.
        _action_substeps(batch)
        with wp.ScopedCapture(device=device) as capture:
            _action_substeps(batch)
        batch.graph = capture.graph
        return
    wp.capture_launch(batch.graph)


# Overflows that make a world's trajectory wrong (MuJoCo Warp's OverflowType bits); an iteration
# limit reached is not one of them.
_OVERFLOWS = {
    1 << 0: "ran out of constraint rows (njmax)",
    1 << 1: "ran out of constraint nonzeros",
    1 << 2: "overflowed its broadphase",
    1 << 3: "ran out of contacts (nconmax)",
    1 << 4: "overflowed its collision buffers (CCD)",
    1 << 7: "overflowed its island buffers",
    1 << 8: "overflowed its EPA buffers",
}


OVERFLOW_BITS = sum(_OVERFLOWS)


def overflow_reason(bits: int) -> str | None:
    for bit, reason in _OVERFLOWS.items():
        if bits & bit:
            return reason
    return None
