"""robosuite's OSC update and torques for one non-policy physics substep, as one numba function.

:func:`osc_substep` does what the exact step path's ``_update`` (after ``mj_jacSite``) and
``ArmStep.control`` do with some 30 numpy calls and three numba dispatches, in one dispatch, with
bit-identical results. Each operation is the one robosuite's step runs, on the same inputs:

- robosuite's numba kernels (``orientation_error``, ``opspace_matrices``, ``nullspace_torques``)
  are called from inside this function on arrays of the layouts robosuite hands them (its
  Jacobian and mass-matrix copies are Fortran-ordered; numba compiles per layout and passes the
  layout on to BLAS), so they run the same code and the same BLAS/LAPACK routines (scipy's).
- numpy's ``np.dot`` of a matrix and a vector calls ``cblas_dgemv`` of numpy's own BLAS, which may
  be another OpenBLAS build than scipy's (numba's ``np.dot`` goes to scipy's). Those products call
  numpy's ``cblas_dgemv`` here too, with the arguments numpy passes (the order from the matrix's
  layout, no transpose, ``alpha`` 1, ``beta`` 0). Where numpy's BLAS is not the one this module
  knows how to reach (:func:`numpy_dgemv_library`), the kernel is not used.
- Copies, gathers, sums, products and clips are element by element: IEEE arithmetic in the same
  order, without fused multiply-adds (numba does not contract them without ``fastmath``).

The compiled code is cached on disk (``cache=True``): a process after the first loads it instead
of compiling it.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import os
from typing import Any

import llvmlite.binding
import numba
import numpy as np
from numba import types
from robosuite.utils.control_utils import nullspace_torques, opspace_matrices, orientation_error

from vecsim.engine.tasks._base import log

# numpy's wheels bundle OpenBLAS built with 64-bit integers and these symbol names.
_DGEMV_SYMBOL = "scipy_cblas_dgemv64_"
_ROW_MAJOR, _COL_MAJOR, _NO_TRANS = 101, 102, 111

# void cblas_dgemv(order, trans, m, n, alpha, a, lda, x, incx, beta, y, incy); the pointers are
# passed as integers (the same registers on the 64-bit ABIs numba targets).
_dgemv = types.ExternalFunction(
    _DGEMV_SYMBOL,
    types.void(
        types.int32,
        types.int32,
        types.int64,
        types.int64,
        types.float64,
        types.intp,
        types.int64,
        types.intp,
        types.int64,
        types.float64,
        types.intp,
        types.int64,
    ),
)


def numpy_dgemv_library() -> str | None:
    """Return the path of the BLAS library numpy calls, where it has :data:`_DGEMV_SYMBOL`, else None."""
    blas = np.show_config(mode="dicts").get("Build Dependencies", {}).get("blas", {})
    if blas.get("name") != "scipy-openblas":
        return None
    site = os.path.dirname(os.path.dirname(os.path.abspath(np.__file__)))
    for path in glob.glob(os.path.join(site, "numpy.libs", "*openblas*")):
        try:
            # RTLD_NOLOAD: only a library numpy has loaded already counts.
            library = ctypes.CDLL(path, mode=os.RTLD_NOLOAD)
        except OSError:
            continue
        if hasattr(library, _DGEMV_SYMBOL):
            return path
    return None


@functools.cache
def available() -> bool:
    """Whether :func:`osc_substep` can run here bit-identically to robosuite's numpy and numba calls.

    Call it (True) before the first :func:`osc_substep`: it loads numpy's BLAS for the kernel's
    symbol lookup.
    """
    kernels = (opspace_matrices, nullspace_torques, orientation_error)
    if numba.config.DISABLE_JIT or not all(isinstance(f, numba.core.dispatcher.Dispatcher) for f in kernels):
        log.info(
            "robosuite's control kernels are not numba-compiled (macros.ENABLE_NUMBA, NUMBA_DISABLE_JIT): "
            "no fused OSC kernel"
        )
        return False
    path = numpy_dgemv_library()
    if path is None:
        log.info("numpy's BLAS is not a bundled scipy-openblas with %s: no fused OSC kernel", _DGEMV_SYMBOL)
        return False
    # The compiled (or cached) kernel finds numpy's cblas_dgemv by name in this library.
    llvmlite.binding.load_library_permanently(path)
    return True


@numba.njit(cache=True)
def _numpy_dot(matrix: Any, vector: Any, out: Any) -> None:
    # np.dot(matrix, vector) as numpy computes it: cblas_dgemv, row-major for a C-ordered matrix,
    # column-major otherwise (all matrices here are contiguous one way or the other).
    rows, cols = matrix.shape
    if matrix.strides[1] == 8 and matrix.strides[0] == 8 * cols:
        order, lda = _ROW_MAJOR, max(cols, 1)
    else:
        order, lda = _COL_MAJOR, max(rows, 1)
    out[:] = 0.0
    _dgemv(
        order,
        _NO_TRANS,
        rows,
        cols,
        1.0,
        matrix.ctypes.data,
        lda,
        vector.ctypes.data,
        vector.strides[0] // 8,
        0.0,
        out.ctypes.data,
        1,
    )


@numba.njit(cache=True)
def _clip(value: float, low: float, high: float) -> float:
    # np.clip's float semantics: max then min, a NaN passes through.
    if not np.isnan(value) and not value > low:
        value = low
    if not np.isnan(value) and not value < high:
        value = high
    return value


@numba.njit(cache=True)
def osc_substep(
    site,
    qpos,
    qvel,
    qM,
    qfrc_bias,
    ctrl,
    site_xpos,
    site_xmat,
    jacp,
    jacr,
    qpos_index,
    qvel_index,
    mass_gather_t,
    arm_ids,
    gripper_ids,
    goal_pos,
    goal_ori,
    kp,
    kd,
    initial_joint,
    torque_low,
    torque_high,
    uncoupling,
    gripper_step,
    gripper_bias,
    gripper_weight,
    ee_pos,
    ee_ori_mat,
    ee_pos_vel,
    ee_ori_vel,
    joint_pos,
    joint_vel,
    j_pos,
    j_ori,
    j_full,
    mass_matrix,
    torques,
    clipped,
    gripper_action,
    wrench,
):
    """One arm's OSC update and control for a non-policy substep, after ``mj_jacSite``.

    Fills the controller's update outputs (``ee_pos`` .. ``mass_matrix``, in the layouts
    robosuite's update gives them: ``j_pos``, ``j_ori``, ``j_full`` and ``mass_matrix``
    Fortran-ordered), its ``torques``, the robot's ``clipped`` torques, the gripper's
    ``gripper_action`` (advanced by ``gripper_step``, as ``PandaGripper.format_action`` does) and
    the arm's and gripper's ``ctrl``. ``wrench`` is scratch (6 floats).
    """
    dof = qvel_index.shape[0]
    # Controller.update
    for i in range(3):
        ee_pos[i] = site_xpos[site, i]
        for j in range(3):
            ee_ori_mat[i, j] = site_xmat[site, 3 * i + j]
    _numpy_dot(jacp, qvel, ee_pos_vel)
    _numpy_dot(jacr, qvel, ee_ori_vel)
    for k in range(dof):
        joint_pos[k] = qpos[qpos_index[k]]
        joint_vel[k] = qvel[qvel_index[k]]
        for i in range(3):
            j_pos[i, k] = jacp[i, qvel_index[k]]
            j_ori[i, k] = jacr[i, qvel_index[k]]
            j_full[i, k] = j_pos[i, k]
            j_full[3 + i, k] = j_ori[i, k]
    for i in range(dof):
        for j in range(dof):
            mass_matrix[i, j] = qM[mass_gather_t[j, i]]
    # OperationalSpaceController.run_controller
    ori_error = orientation_error(goal_ori, ee_ori_mat)
    desired_force = np.empty(3)
    desired_torque = np.empty(3)
    for i in range(3):
        desired_force[i] = (goal_pos[i] - ee_pos[i]) * kp[i] + (-ee_pos_vel[i]) * kd[i]
        desired_torque[i] = ori_error[i] * kp[3 + i] + (-ee_ori_vel[i]) * kd[3 + i]
    lambda_full, lambda_pos, lambda_ori, nullspace_matrix = opspace_matrices(mass_matrix, j_full, j_pos, j_ori)
    if uncoupling:
        _numpy_dot(lambda_pos, desired_force, wrench[0:3])
        _numpy_dot(lambda_ori, desired_torque, wrench[3:6])
    else:
        desired_wrench = np.empty(6)
        desired_wrench[0:3] = desired_force
        desired_wrench[3:6] = desired_torque
        _numpy_dot(lambda_full, desired_wrench, wrench)
    _numpy_dot(j_full.T, wrench, torques)
    for k in range(dof):
        torques[k] = torques[k] + qfrc_bias[qvel_index[k]]
    nullspace = nullspace_torques(mass_matrix, nullspace_matrix, initial_joint, joint_pos, joint_vel)
    for k in range(dof):
        torques[k] = torques[k] + nullspace[k]
    # SingleArm.control: clipped torques, the gripper's action, both into ctrl.
    for k in range(dof):
        clipped[k] = _clip(torques[k], torque_low[k], torque_high[k])
    for g in range(gripper_ids.shape[0]):
        gripper_action[g] = _clip(gripper_action[g] + gripper_step[g], -1.0, 1.0)
        ctrl[gripper_ids[g]] = gripper_bias[g] + gripper_weight[g] * gripper_action[g]
    for k in range(dof):
        ctrl[arm_ids[k]] = clipped[k]
