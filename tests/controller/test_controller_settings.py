"""The controller's settings extend the job file's ``controller`` section: every field of the
section is declared once, in ``vecsim.config.ControllerConfig``, and reaches the controller with
the value the job file gave it."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from service.controller.settings import ControllerSettings
from service.pod.settings import PodSettings
from vecsim.config import ControllerConfig, HeartbeatConfig, JobConfig, JobSpec


def test_every_field_of_the_job_files_controller_section_is_a_controller_setting_of_the_same_declaration():
    for name, field in ControllerConfig.model_fields.items():
        setting = ControllerSettings.model_fields[name]
        assert (setting.default, setting.metadata) == (field.default, field.metadata), name


def test_the_pod_and_the_controller_take_the_heartbeat_interval_from_one_declaration():
    field = HeartbeatConfig.model_fields["heartbeat_interval_s"]
    for settings in (ControllerSettings, PodSettings):
        assert settings.model_fields["heartbeat_interval_s"].metadata == field.metadata


def test_a_job_files_controller_section_reaches_the_controllers_settings_whole():
    section = ControllerConfig(
        host="0.0.0.0", port=8123, heartbeat_interval_s=0.5, heartbeat_ttl_s=2.0, reconcile_interval_s=0.25
    )
    job = JobSpec(job_id="j", tasks=("gym/HalfCheetah-v5",), group_size=1)
    settings = ControllerSettings.from_job_config(JobConfig(job=job, controller=section))
    assert settings.model_dump(include=set(ControllerConfig.model_fields)) == section.model_dump()
    assert settings.job == job


@pytest.mark.parametrize(("field", "value"), [("port", 0), ("port", 70000), ("heartbeat_ttl_s", 0.0)])
def test_a_bad_value_is_refused_alike_in_the_job_file_and_the_settings(field: str, value: object):
    for model in (ControllerConfig, ControllerSettings):
        with pytest.raises(ValidationError, match=field):
            model(**{field: value})
