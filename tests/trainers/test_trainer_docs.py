"""docs/trainers.md's RLinf instructions, run as pasted against RLinf's own env selection.

The python block is executed as written; the yaml block is read by OmegaConf as RLinf reads its
config, and RLinf's own ``get_env_cls`` (``rlinf/envs/__init__.py``) then picks vecsim's env for
the documented ``env.train`` block and RLinf's own LIBERO env without the ``vecsim`` key. What the
chosen class does is tests/trainers/test_trainer_rlinf.py's; the verl-vla and LeRobot
instructions run as pasted in their own test modules.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

pytest.importorskip("rlinf")
from omegaconf import OmegaConf  # noqa: E402

import vecsim.trainers.rlinf  # noqa: E402
from vecsim.engine.tasks._libero import ensure_config  # noqa: E402

DOCS = Path(__file__).resolve().parents[2] / "docs" / "trainers.md"


def _blocks(section: str, language: str) -> list[str]:
    text = DOCS.read_text().split(f"## {section}", 1)[1].split("\n## ", 1)[0]
    return re.findall(rf"```{language}\n(.*?)```", text, re.DOTALL)


def test_the_rlinf_instructions_make_rlinfs_env_selection_pick_vecsims_env():
    for block in _blocks("RLinf", "python"):
        exec(compile(block, str(DOCS), "exec"), {})
    import rlinf.envs

    train = OmegaConf.create(_blocks("RLinf", "yaml")[0]).env.train
    assert rlinf.envs.get_env_cls(train.env_type, train) is vecsim.trainers.rlinf.VecsimLiberoEnv
    del train["vecsim"]
    ensure_config()  # RLinf's LIBERO env imports LIBERO, which asks for its paths on stdin without one
    assert rlinf.envs.get_env_cls(train.env_type, train).__module__ == "rlinf.envs.libero.libero_env"
