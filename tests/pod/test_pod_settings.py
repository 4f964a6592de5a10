"""A pod's settings from its environment (``PodSettings.from_env``, through
``vecsim.envsettings.from_environ`` as the mjwarp engine's): a value that cannot be used is refused
naming the variable or flag and the value given, but a token's value is never shown."""

from __future__ import annotations

import pytest

from service.pod.settings import PodSettings
from vecsim.envsettings import SettingsError


def test_a_malformed_variable_is_refused_naming_it_and_its_value() -> None:
    with pytest.raises(SettingsError) as refused:
        PodSettings.from_env({"VECSIM_PORT": "80x", "VECSIM_MAX_ENVS": "64"})
    assert "environment variable VECSIM_PORT is '80x'" in str(refused.value)
    assert "VECSIM_MAX_ENVS" not in str(refused.value)


def test_a_flag_overrides_the_variable_and_is_named_when_refused() -> None:
    assert PodSettings.from_env({"VECSIM_PORT": "80x"}, port=8101).port == 8101
    with pytest.raises(SettingsError, match="setting 'port' is 0"):
        PodSettings.from_env({}, port=0)


def test_an_empty_variable_is_unset() -> None:
    assert PodSettings.from_env({"VECSIM_PORT": ""}).port == PodSettings().port


def test_a_refused_token_is_named_without_its_value() -> None:
    secret = "not a token"
    with pytest.raises(SettingsError, match="VECSIM_TOKEN") as refused:
        PodSettings.from_env({"VECSIM_TOKEN": secret})
    assert secret not in str(refused.value)
