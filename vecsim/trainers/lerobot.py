"""LeRobotVectorEnv: a vecsim LIBERO job as LeRobot's eval loop drives its LIBERO vector env.

LeRobot's ``lerobot_eval.rollout``/``eval_policy`` (lerobot 0.4.4, ``src/lerobot/scripts/
lerobot_eval.py``) read more of a vector env than gymnasium's API: ``env.envs[0]`` with
``task_description`` and ``task`` (``envs/utils.py``: ``check_env_attributes_and_types``,
``add_envs_task``), ``call("_max_episode_steps")``, ``info["final_info"]["is_success"]``, frames
from ``call("render")`` when the env is an ``AsyncVectorEnv`` and ``unwrapped.metadata
["render_fps"]`` for its videos. This class gives them over :class:`HTTPVectorEnv`, with
LeRobot's LIBERO observation layout (``envs/libero.py``, ``obs_type="pixels_agent_pos"``).

Example::

    # a job with libero: {image_orientation: raw}, n envs of the task
    env = LeRobotVectorEnv(pod_urls=["http://127.0.0.1:8000"])
    info = eval_policy(env, policy, env_pre, env_post, pre, post, n_episodes=env.num_envs, start_seed=1000)
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.vector import AsyncVectorEnv
from gymnasium.vector.vector_env import AutoresetMode

from vecsim.client.vector_env import HTTPVectorEnv
from vecsim.client.vector_resets import StateDraws, env_seeds, reset_mask
from vecsim.config import LEROBOT_RESETS

__all__ = ["LEROBOT_CAMERA_KEYS", "LeRobotVectorEnv"]

# LeRobot's LiberoEnv names agentview "image" and the wrist camera "image2" (envs/libero.py,
# LiberoEnv.__init__'s default camera_name_mapping).
LEROBOT_CAMERA_KEYS: dict[str, str] = {"agentview": "image", "robot0_eye_in_hand": "image2"}
# LiberoEnv.metadata (envs/libero.py): eval_policy writes its videos at this rate.
LEROBOT_RENDER_FPS = 80

# numpy's legacy seeding (LIBERO's env.seed) takes 0..2**32 - 1.
_MAX_LIBERO_SEED = 2**32 - 1
# Offsets of the pods' 23-float ``proprio`` (vecsim.engine.tasks._robot.PROPRIO_KEYS).
_COS, _SIN, _EEF_POS, _EEF_QUAT, _GRIPPER_QPOS = slice(0, 7), slice(7, 14), slice(14, 17), slice(17, 21), slice(21, 23)


def _robot_state_space() -> spaces.Dict:
    box = lambda *shape: spaces.Box(-np.inf, np.inf, shape=shape, dtype=np.float64)  # noqa: E731
    return spaces.Dict(
        {
            "eef": spaces.Dict({"pos": box(3), "quat": box(4)}),
            "gripper": spaces.Dict({"qpos": box(2)}),
            "joints": spaces.Dict({"pos": box(7)}),
        }
    )


class _EnvView:
    """Env ``i`` of a :class:`LeRobotVectorEnv`, as LeRobot reads ``env.envs[i]``."""

    def __init__(self, vector: LeRobotVectorEnv, index: int) -> None:
        self._vector, self._index = vector, index
        self.task = vector.task_ids[index]
        self.task_description = vector.client.instructions[self.task]
        self.metadata = vector.metadata

    @property
    def _max_episode_steps(self) -> int:
        return self._vector.max_episode_steps[self._index]

    @property
    def unwrapped(self) -> _EnvView:
        return self

    def render(self) -> np.ndarray:
        """This env's frame: the first camera of its last observation, as LeRobot renders it."""
        return self._vector.render_frames()[self._index]


class _LeRobotDraws(StateDraws):
    """State ids as LeRobot's ``LiberoEnv`` takes them: env ``i`` of ``n`` starts its ``k``-th
    reset (every reset counted: its own, the one inside a terminating step, the autoreset after
    it) in init state ``(i + k * n) % num_states``."""

    def __init__(self, task_ids: list[str], num_states: Mapping[str, int]) -> None:
        super().__init__(task_ids, num_states)
        self.resets = np.zeros(len(task_ids), dtype=np.int64)  # each env's resets so far

    def next_state(self, i: int) -> int:
        """Env ``i``'s next ``init_state_id``."""
        return int((i + self.resets[i] * len(self.task_ids)) % self.num_states[self.task_ids[i]])

    def draw(self, i: int, reseeded: Any = None) -> int:
        """An unseeded reset or autoreset of env ``i``: its next ``init_state_id``, counted."""
        state_id = self.next_state(i)
        self.resets[i] += 1
        return state_id


class LeRobotVectorEnv(HTTPVectorEnv, AsyncVectorEnv):
    """:class:`HTTPVectorEnv` as LeRobot's eval loop reads a LIBERO vector env.

    Arguments are :class:`HTTPVectorEnv`'s, plus ``camera_keys`` (vecsim camera name -> LeRobot's
    ``pixels`` key; LeRobot's own by default) and ``render_fps`` (the videos' rate).

    - Observations: ``{"pixels": {"image", "image2"}, "robot_state": {"eef": {"pos", "quat"},
      "gripper": {"qpos"}, "joints": {"pos"}}}`` as float64, what LeRobot's
      ``LiberoProcessorStep`` reads. Images come as the job serves them: LeRobot flips LIBERO's
      raw frames itself, so serve them with ``libero: {image_orientation: raw}``. LeRobot's
      ``eef.mat``, ``gripper.qvel`` and ``joints.vel`` are not served.
    - Resets as LeRobot's ``LiberoEnv`` resets: env ``i``'s ``r``-th reset (counting those its
      env makes itself when an episode terminates, and the vector env's autoreset after it)
      takes init state ``(i + r * n) % 50`` (``n`` envs), LeRobot's ``init_state_id`` sequence,
      unless ``options["state_ids"]`` names them. A seeded reset is LeRobot's
      ``env.seed(seed); env.reset()`` after ``r`` earlier ones: the pods replay its fixture
      placement and arm pose (the reset option ``vecsim.config.LEROBOT_RESETS``). Other reset
      options LeRobot passes are ignored.
    - ``info["is_success"]`` beside ``success``; an env that ends a step has
      ``info["final_info"]["is_success"]`` (NEXT_STEP and SAME_STEP).
    - ``envs[i]`` has ``task`` (the vecsim task id), ``task_description`` (the instruction),
      ``_max_episode_steps`` and ``render()``; ``call``/``get_attr`` answer those names too,
      ``call("render")``/``render()`` give each env's frame: its first camera's image of the last
      observation, turned as LeRobot's ``LiberoEnv.render`` turns it (``raw[::-1, ::-1]``).

    It is an ``AsyncVectorEnv`` by type only, so that LeRobot's ``eval_policy`` takes frames
    through ``call("render")``; every method is :class:`HTTPVectorEnv`'s or this class's.
    """

    def __init__(
        self,
        *args: Any,
        camera_keys: Mapping[str, str] | None = None,
        render_fps: int = LEROBOT_RENDER_FPS,
        **kwargs: Any,
    ) -> None:
        """Connect as :class:`HTTPVectorEnv` does.

        Raises:
            ValueError: the job's observations are not a robot task's ``images``/``proprio``
                (names what is missing), or a camera of ``camera_keys`` the job does not serve.
            as :class:`HTTPVectorEnv`.
        """
        super().__init__(*args, **kwargs)
        try:
            self._setup_lerobot(dict(LEROBOT_CAMERA_KEYS if camera_keys is None else camera_keys), render_fps)
        except BaseException:
            self.close()
            raise

    def _setup_lerobot(self, camera_keys: dict[str, str], render_fps: int) -> None:
        served = self.single_observation_space
        if not isinstance(served, spaces.Dict) or "images" not in served.spaces or "proprio" not in served.spaces:
            raise ValueError(
                f"LeRobotVectorEnv serves LIBERO/robot tasks (observations with 'images' and 'proprio'); "
                f"this job's observation space is {served}"
            )
        cameras = list(served["images"].spaces)
        unknown = sorted(set(camera_keys) - set(cameras))
        if unknown:
            raise ValueError(f"camera_keys names camera(s) {unknown} the job does not serve; it serves {cameras}")
        self.camera_keys = {name: camera_keys[name] for name in cameras if name in camera_keys}
        self._render_camera = cameras[0]
        self.single_observation_space = spaces.Dict(
            {
                "pixels": spaces.Dict({key: served["images"][name] for name, key in self.camera_keys.items()}),
                "robot_state": _robot_state_space(),
            }
        )
        self.observation_space = spaces.Dict(
            {
                "pixels": spaces.Dict(
                    {
                        key: spaces.Box(0, 255, (self.num_envs, *served["images"][name].shape), np.uint8)
                        for name, key in self.camera_keys.items()
                    }
                ),
                "robot_state": _batched(_robot_state_space(), self.num_envs),
            }
        )
        self.metadata = {**self.metadata, "render_modes": ["rgb_array"], "render_fps": render_fps}
        self.render_mode = "rgb_array"
        self.max_episode_steps = tuple(int(steps) for steps in super()._attr("get_attr", "max_episode_steps", None))
        self.envs = [_EnvView(self, i) for i in range(self.num_envs)]

    # -- resets as LeRobot's LiberoEnv makes them ------------------------------------------------

    def reset_async(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> None:
        """:meth:`HTTPVectorEnv.reset_async`; with seeds, each env's reset is LeRobot's under its
        seed (see the class docstring).

        Raises:
            ValueError: some reset envs seeded and others not, or a seed outside
                ``0..2**32 - 1`` (LIBERO's ``env.seed`` takes no other; named).
            as :meth:`HTTPVectorEnv.reset_async`.
        """
        options = dict(options or {})
        plan = self._lerobot_plan(seed, options)
        if plan is None:
            super().reset_async(seed=seed, options=options)
            return
        # LeRobot's reset is each LIBERO env's own seeded reset (see _resets_itself), with the
        # plan as the options every env of the call reads.
        super().reset_async(seed=seed, options={**options, LEROBOT_RESETS: plan})
        self._draws.resets[reset_mask(options.get("reset_mask"), self.num_envs)] += 1

    def _resets_itself(self, options: dict[str, Any]) -> bool:
        """A reset carrying LeRobot's plan is the LIBERO envs' own seeded reset."""
        return LEROBOT_RESETS in options or super()._resets_itself(options)

    def _lerobot_plan(self, seed: Any, options: dict[str, Any]) -> dict[str, dict[str, int]] | None:
        """The reset option :data:`LEROBOT_RESETS` for a seeded reset, None for the others."""
        if options.get("state_ids") is not None:
            return None
        seeds, mask = env_seeds(seed, self.num_envs), reset_mask(options.get("reset_mask"), self.num_envs)
        reset = np.flatnonzero(mask).tolist()
        seeded = [i for i in reset if seeds[i] is not None]
        if not seeded:
            return None
        if len(seeded) != len(reset):
            unseeded = sorted(set(reset) - set(seeded))
            raise ValueError(f"seed: envs {unseeded} have no seed beside seeded ones; seed every env reset, or none")
        plan: dict[str, dict[str, int]] = {}
        for i in seeded:
            if seeds[i] > _MAX_LIBERO_SEED:
                raise ValueError(f"seed for env {i} is {seeds[i]}; LIBERO's env.seed takes 0..{_MAX_LIBERO_SEED}")
            entry = {"state_id": self._draws.next_state(i), "resets_before": int(self._draws.resets[i])}
            if plan.setdefault(str(seeds[i]), entry) != entry:
                raise ValueError(
                    f"seed {seeds[i]} is given to envs of different init states; give each env its own seed"
                )
        return plan

    def _state_draws(self, task_ids: list[str], num_states: dict[str, int]) -> StateDraws:
        return _LeRobotDraws(task_ids, num_states)

    # -- answers in LeRobot's layout ------------------------------------------------------------

    def reset_wait(self, timeout: float | None = None) -> tuple[Any, dict[str, Any]]:
        """:meth:`HTTPVectorEnv.reset_wait`, in LeRobot's layout with ``is_success``."""
        obs, info = super().reset_wait(timeout)
        return self._layout(obs), _with_is_success(info)

    def step_wait(self, timeout: float | None = None) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """:meth:`HTTPVectorEnv.step_wait`, in LeRobot's layout with ``is_success`` and, for envs
        that ended, ``final_info["is_success"]``."""
        obs, reward, terminated, truncated, info = super().step_wait(timeout)
        info = _with_is_success(info)
        # LeRobot's LiberoEnv.step resets the env itself when it terminates (never truncates).
        self._draws.resets += terminated if terminated.ndim == 1 else terminated.any(axis=1)
        ended = terminated | truncated
        ended = ended if ended.ndim == 1 else ended.any(axis=1)
        if "final_info" in info:  # SAME_STEP: the step's own info of the envs that were reset
            info["final_info"] = _with_is_success(info["final_info"])
        elif ended.any() and self.autoreset_mode != AutoresetMode.SAME_STEP:
            # LeRobot's LiberoEnv.step puts final_info in the info of the step that ends (envs/libero.py).
            final = {"is_success": np.where(ended, info["is_success"], False), "_is_success": ended.copy()}
            info["final_info"], info["_final_info"] = final, ended.copy()
        return self._layout(obs), reward, terminated, truncated, info

    def _layout(self, obs: dict[str, Any]) -> dict[str, Any]:
        proprio = obs["proprio"].astype(np.float64)  # float64 as served: LIBERO's observables
        return {
            "pixels": {key: obs["images"][name] for name, key in self.camera_keys.items()},
            "robot_state": {
                "eef": {"pos": proprio[:, _EEF_POS], "quat": proprio[:, _EEF_QUAT]},
                "gripper": {"qpos": proprio[:, _GRIPPER_QPOS]},
                "joints": {"pos": np.arctan2(proprio[:, _SIN], proprio[:, _COS])},
            },
        }

    # -- frames and attributes ------------------------------------------------------------------

    def render_frames(self) -> np.ndarray:
        """Every env's frame ``[num_envs, H, W, 3]``: its first camera's image of the last
        observation, turned 180 degrees (``raw[::-1, ::-1]``, LeRobot's ``LiberoEnv.render``)."""
        self._assert_open()
        return np.ascontiguousarray(self._results.obs["images"][self._render_camera][:, ::-1, ::-1])

    def render(self) -> tuple[np.ndarray, ...]:
        """Each env's frame (see :meth:`render_frames`)."""
        return tuple(self.render_frames())

    def _attr(self, op: str, name: str, payload: Any) -> list[Any]:
        if op != "set_attr" and name in ("task", "task_description", "_max_episode_steps"):
            self._assert_open()
            return [getattr(view, name) for view in self.envs]
        if op == "call" and name == "render":
            return list(self.render_frames())
        return super()._attr(op, name, payload)

    def call_async(self, name: str, *args: Any, **kwargs: Any) -> None:
        """Run :meth:`call` now; :meth:`call_wait` hands its result over (AsyncVectorEnv's pair)."""
        self._call_result = self.call(name, *args, **kwargs)

    def call_wait(self, timeout: float | None = None) -> tuple[Any, ...]:
        """The result of the last :meth:`call_async`.

        Raises:
            NoAsyncCallError: no call_async came first.
        """
        from gymnasium.error import NoAsyncCallError

        result = getattr(self, "_call_result", None)
        if result is None:
            raise NoAsyncCallError("Calling `call_wait` without any prior call to `call_async`.", "call")
        self._call_result = None
        return result

    @property
    def np_random(self) -> Any:
        return HTTPVectorEnv.np_random.fget(self)  # type: ignore[attr-defined]


def _batched(space: spaces.Dict, n: int) -> spaces.Dict:
    return spaces.Dict(
        {
            key: _batched(sub, n)
            if isinstance(sub, spaces.Dict)
            else spaces.Box(-np.inf, np.inf, (n, *sub.shape), sub.dtype)
            for key, sub in space.spaces.items()
        }
    )


def _with_is_success(info: dict[str, Any]) -> dict[str, Any]:
    """``info`` with LeRobot's ``is_success`` (and its mask) beside vecsim's ``success``."""
    info = copy.copy(info)
    if "success" in info:
        info["is_success"], info["_is_success"] = info["success"].copy(), info["_success"].copy()
    return info
