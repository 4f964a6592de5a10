"""Stand in for ``torchvision`` where it cannot be imported, for LeRobot's imports only.

LeRobot imports torchvision at module level in code the eval loop never runs (dataset image
transforms, the human-in-the-loop crop step, vision backbones). PyPI's torchvision wheels link
against CUDA torch and do not load beside the venv's CPU torch (``libtorch_cuda.so`` missing),
so :func:`install` puts a placeholder ``torchvision`` package on ``sys.meta_path``: every module
and attribute of it exists, and *using* any of them raises ``RuntimeError``. A test that needs
torchvision's behaviour therefore fails loudly instead of running on a fake.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import importlib.util
import sys
import types


class _Unavailable:
    """A placeholder attribute: it can be named and subclassed, never used."""

    _where = "torchvision"

    def __init__(self, *args: object, **kwargs: object) -> None:
        raise RuntimeError(f"{self._where} was used, but torchvision is not importable beside this torch")

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__()


def _placeholder(module: str, name: str) -> type:
    return type(name, (_Unavailable,), {"_where": f"{module}.{name}", "__module__": module})


class _Module(types.ModuleType):
    def __getattr__(self, name: str) -> object:
        if name.startswith("__"):
            raise AttributeError(name)
        full = f"{self.__name__}.{name}"
        if full in sys.modules:
            return sys.modules[full]
        value = _placeholder(self.__name__, name)
        setattr(self, name, value)
        return value


class _Finder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def find_spec(self, fullname: str, path: object, target: object = None) -> importlib.machinery.ModuleSpec | None:
        if fullname == "torchvision" or fullname.startswith("torchvision."):
            return importlib.machinery.ModuleSpec(fullname, self, is_package=True)
        return None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        module = _Module(spec.name)
        module.__path__ = []
        module.__version__ = "0+absent"
        return module

    def exec_module(self, module: types.ModuleType) -> None:
        parent, _, child = module.__name__.rpartition(".")
        if parent and parent in sys.modules:
            setattr(sys.modules[parent], child, module)


def install() -> bool:
    """Put the placeholder in place if torchvision cannot be imported; return whether it did."""
    try:
        import torchvision  # noqa: F401
    except Exception:
        for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
            del sys.modules[name]
        sys.meta_path.insert(0, _Finder())
        return True
    return False
