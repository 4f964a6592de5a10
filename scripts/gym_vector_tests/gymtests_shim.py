"""Registers gymnasium's test envs (tests/vector/testing_utils.py) for the pods: a pod makes
``gymtests_shim:SlowEnv-v0`` by importing this module, then making ``SlowEnv-v0``."""

import gymnasium

gymnasium.register("SlowEnv-v0", entry_point="tests.vector.testing_utils:SlowEnv")
gymnasium.register("CustomSpaceEnv-v0", entry_point="tests.vector.testing_utils:CustomSpaceEnv")
