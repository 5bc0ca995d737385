"""teletouch: a camera-based tactile sensor (DIGIT) as a force sensor, and position-force teleoperation with it.

The core is small: components (:mod:`teletouch.component`), plugin discovery (:mod:`teletouch.registry`, pluggy,
entry-point group ``teletouch``), YAML graphs (:mod:`teletouch.graph`) and a multi-rate runtime
(:mod:`teletouch.runtime`). Sensors, estimators, devices and controllers are plugins under ``teletouch.plugins``.
"""

from __future__ import annotations

__version__ = "0.1.0"

from .component import Component, Context, Device, Inputs, Kind, Params, Port, Sample  # noqa: E402
from .errors import (  # noqa: E402
    ComponentFault, GraphError, GraphValidationError, HardwareError, ModelFileError, PluginError, TeletouchError,
)
from .hookspecs import hookimpl  # noqa: E402

__all__ = [
    "__version__", "Component", "Context", "Device", "Inputs", "Kind", "Params", "Port", "Sample", "hookimpl",
    "ComponentFault", "GraphError", "GraphValidationError", "HardwareError", "ModelFileError", "PluginError",
    "TeletouchError",
]
