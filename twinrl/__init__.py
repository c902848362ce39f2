"""twinrl: robot learning through differentiable digital twins (Real2Sim -> Learn@Sim -> Sim2Real).

``import twinrl`` applies the JAX settings (``twinrl._jaxconfig``) and gives every sub-package as
an attribute (``twinrl.envs``, ``twinrl.physics``, ...), imported on first use (PEP 562), so a
command that needs only the physics does not pay for the learners' imports.
"""

import importlib

from twinrl import _jaxconfig

_jaxconfig.set_cpu_flags()
_jaxconfig.enable_compilation_cache()
_jaxconfig.import_mjx_quietly()

__version__ = "0.1.0"

_SUBMODULES = ("envs", "eval", "learn", "loop", "physics", "real", "real2sim", "render", "report",
               "sim2real", "cli")


def __getattr__(name: str):
    if name in _SUBMODULES:
        return importlib.import_module(f"twinrl.{name}")  # also sets it as an attribute
    raise AttributeError(f"module 'twinrl' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_SUBMODULES))
