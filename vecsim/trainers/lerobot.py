"""LeRobotVectorEnv: a vecsim LIBERO job as LeRobot's eval loop drives its LIBERO vector env.

LeRobot's ``lerobot_eval.rollout``/``eval_policy`` (lerobot 0.4.4, ``src/lerobot/scripts/
lerobot_eval.py``) read more of a vector env than gymnasium's API: ``env.envs[0]`` with
``task_description`` and ``task`` (``envs/utils.py``: ``check_env_attributes_and_types``,
``add_envs_task``), ``call("_max_episode_steps")``, ``info["final_info"]["is_success"]``, frames
from ``call("render")`` when the env is an ``AsyncVectorEnv`` and ``unwrapped.metadata
["render_fps"]`` for its videos. This class gives them over :class:`HTTPVectorEnv`, with
LeRobot's LIBERO observation layout (``envs/libero.py``, ``obs_type="pixels_agent_pos"``).

Example::

    # a job with libero: {image_orientation: raw, fixture_rule: lerobot, fixture_seed: 0, fixture_stride: 2}
    env = LeRobotVectorEnv(pod_urls=["http://127.0.0.1:8000"])
    info = eval_policy(env, policy, env_pre, env_post, pre, post, n_episodes=env.num_envs, start_seed=0)
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.vector import AsyncVectorEnv
from gymnasium.vector.vector_env import AutoresetMode

from vecsim.client.vector_env import HTTPVectorEnv

__all__ = ["LEROBOT_CAMERA_KEYS", "LeRobotVectorEnv"]

# LeRobot's LiberoEnv names agentview "image" and the wrist camera "image2" (envs/libero.py,
# LiberoEnv.__init__'s default camera_name_mapping).
LEROBOT_CAMERA_KEYS: dict[str, str] = {"agentview": "image", "robot0_eye_in_hand": "image2"}
# LiberoEnv.metadata (envs/libero.py): eval_policy writes its videos at this rate.
LEROBOT_RENDER_FPS = 80

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


class LeRobotVectorEnv(HTTPVectorEnv, AsyncVectorEnv):
    """:class:`HTTPVectorEnv` as LeRobot's eval loop reads a LIBERO vector env.

    Arguments are :class:`HTTPVectorEnv`'s, plus ``camera_keys`` (vecsim camera name -> LeRobot's
    ``pixels`` key; LeRobot's own by default) and ``render_fps`` (the videos' rate).

    - Observations: ``{"pixels": {"image", "image2"}, "robot_state": {"eef": {"pos", "quat"},
      "gripper": {"qpos"}, "joints": {"pos"}}}`` as float64, what LeRobot's
      ``LiberoProcessorStep`` reads. Images come as the job serves them: LeRobot flips LIBERO's
      raw frames itself, so serve them with ``libero: {image_orientation: raw}``. LeRobot's
      ``eef.mat``, ``gripper.qvel`` and ``joints.vel`` are not served.
    - Resets: env ``i``'s resets take initial states ``i, i + n, i + 2n, ...`` (``n`` envs),
      LeRobot's ``init_state_id`` sequence, unless ``options["state_ids"]`` names them; reset
      options LeRobot passes are ignored. LeRobot's seeds place LIBERO's fixtures: the job's
      ``libero.fixture_rule: lerobot`` places them as LeRobot's env does (docs/trainers.md).
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
                    {key: spaces.Box(0, 255, (self.num_envs, *served["images"][name].shape), np.uint8) for name, key in self.camera_keys.items()}
                ),
                "robot_state": _batched(_robot_state_space(), self.num_envs),
            }
        )
        self.metadata = {**self.metadata, "render_modes": ["rgb_array"], "render_fps": render_fps}
        self.render_mode = "rgb_array"
        self._next_state = np.arange(self.num_envs, dtype=np.int64)
        self.max_episode_steps = tuple(int(steps) for steps in super()._attr("get_attr", "max_episode_steps", None))
        self.envs = [_EnvView(self, i) for i in range(self.num_envs)]

    # -- resets in LeRobot's init-state order ---------------------------------------------------

    def _draw_state_id(self, i: int, reseeded: Any = None) -> int:
        """LeRobot's ``LiberoEnv.reset``: env ``i``'s ``init_state_id`` goes ``i, i + n, ...``
        (modulo the task's states), whatever the seed (the seed only seeds LIBERO's placements)."""
        state_id = int(self._next_state[i] % self._num_states[self.task_ids[i]])
        self._next_state[i] += self.num_envs
        return state_id

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
        proprio = obs["proprio"].astype(np.float64)
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
        return np.ascontiguousarray(self._obs["images"][self._render_camera][:, ::-1, ::-1])

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
            key: _batched(sub, n) if isinstance(sub, spaces.Dict) else spaces.Box(-np.inf, np.inf, (n, *sub.shape), sub.dtype)
            for key, sub in space.spaces.items()
        }
    )


def _with_is_success(info: dict[str, Any]) -> dict[str, Any]:
    """``info`` with LeRobot's ``is_success`` (and its mask) beside vecsim's ``success``."""
    info = copy.copy(info)
    if "success" in info:
        info["is_success"], info["_is_success"] = info["success"].copy(), info["_success"].copy()
    return info
