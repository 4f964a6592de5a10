"""Settings read from environment variables into a pydantic model, each error naming its variable.

The pod's settings (``service.pod.settings.PodSettings``) and the mjwarp engine's
(``vecsim.engine.mjwarp.settings.MjwarpSettings``) are read this way, so a value that cannot be
used is refused the same way wherever it is set::

    settings = from_environ(PodSettings, {"VECSIM_PORT": "port"}, {"VECSIM_PORT": "80x"})
    # SettingsError: environment variable VECSIM_PORT is '80x': Input should be a valid integer, ...
"""

from __future__ import annotations

import os
from collections.abc import Collection, Mapping
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

Model = TypeVar("Model", bound=BaseModel)


class SettingsError(ValueError):
    """Settings that cannot be used; the message names the variable or flag at fault."""


def from_environ(
    model: type[Model],
    env_vars: Mapping[str, str],
    environ: Mapping[str, str] | None = None,
    overrides: Mapping[str, Any] | None = None,
    *,
    keep_empty: Collection[str] = (),
) -> Model:
    """``model`` from the variables of ``env_vars`` (variable -> field) set in ``environ``
    (default ``os.environ``), then ``overrides`` (field -> value) on top.

    An empty variable counts as unset (the field keeps its default), except those named in
    ``keep_empty``, whose empty value means something. An override of None is ignored, so that
    unset command-line flags fall through.

    Returns:
        The validated settings.

    Raises:
        SettingsError: every field at fault, each named by its variable (or ``setting 'field'``
            for an override) with the value given, but for a field kept out of its model's
            ``repr`` (a token).
    """
    environ = os.environ if environ is None else environ
    values: dict[str, Any] = {}
    source: dict[str, str] = {}
    for var, field in env_vars.items():
        raw = environ.get(var)
        if raw is not None and (raw != "" or var in keep_empty):
            values[field] = raw
            source[field] = f"environment variable {var}"
    for field, value in (overrides or {}).items():
        if value is not None:
            values[field] = value
            source[field] = f"setting {field!r}"
    try:
        return model.model_validate(values)
    except ValidationError as exc:
        problems = "; ".join(_problem(model, error, values, source) for error in exc.errors())
        raise SettingsError(problems) from exc


def _problem(model: type[BaseModel], error: Any, values: Mapping[str, Any], source: Mapping[str, str]) -> str:
    if not error["loc"]:
        return f"<root>: {error['msg']}"
    field = str(error["loc"][0])
    where = source.get(field, field)
    info = model.model_fields.get(field)
    if field in values and (info is None or info.repr):
        return f"{where} is {values[field]!r}: {error['msg']}"
    return f"{where}: {error['msg']}"
