"""Registers gymnasium's test envs (tests/vector/testing_utils.py) as ids a vecsim pod can make."""

import gymnasium

gymnasium.register("gymtests_shim:SlowEnv-v0", entry_point="tests.vector.testing_utils:SlowEnv")
gymnasium.register("gymtests_shim:CustomSpaceEnv-v0", entry_point="tests.vector.testing_utils:CustomSpaceEnv")
