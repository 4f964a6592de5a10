"""The ``mjwarp`` engine: a pod's LIBERO envs as MuJoCo Warp worlds on one GPU (docs/mjwarp.md).

- ``scene``: a task's compiled model, init states and settled resets, exported from the CPU
  engine (robosuite, LIBERO) and cached on disk; read back with numpy alone;
- ``engine``: the engine the pod builds (``KIND``), in an environment of its own (the
  ``mjwarp`` extra: mujoco 4, warp, mujoco-warp; no robosuite or LIBERO);
- ``settings``: its ``VECSIM_MJWARP_*`` environment variables, checked when an engine is built;
- ``controller``, ``observables``, ``predicates``: robosuite's OSC_POSE and gripper control,
  the observations a policy reads and LIBERO's success predicates, batched over worlds in Warp.

Nothing here is imported by ``vecsim.engine`` itself: the pod reaches it through
``vecsim.engine.base.engine_kind("mjwarp")``.
"""
