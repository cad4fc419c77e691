"""jaxinertia: mass and centre of mass of a held object from servo encoder discrepancies."""

from jaxinertia import _xla_workarounds

_xla_workarounds.apply()

__version__ = "0.1.0"
