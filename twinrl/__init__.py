"""twinrl: robot learning through differentiable digital twins (Real2Sim -> Learn@Sim -> Sim2Real)."""

from twinrl import _jaxconfig

_jaxconfig.enable_compilation_cache()
_jaxconfig.import_mjx_quietly()

__version__ = "0.1.0"
