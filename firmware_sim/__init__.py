"""Simulated BMI camera firmware: registers, sensor readout, RAW12 framing with CRC, transport, faults.

Public API (the rest is private):

* ``FirmwareDevice`` — one simulated camera (register file, readout, faults);
* ``FirmwareServer`` — serves a device over TCP on loopback; ``InProcessLink``
  serves it over an in-process socket pair;
* ``FaultPlan`` / ``Fault`` — seeded fault injection;
* optical sources (``RenderedScene``, ``procedural:SEED``): scenes seen
  through the lens by the forward simulator (``optical``);
* irradiance sources (``IrradianceSource`` protocol, ``FlatField``,
  ``DarkFrame``, ``PolarChart``, ``InFocusImageStandIn``) and the
  ``register_source`` / ``make_source`` registry the forward simulator plugs into.

The register map and the wire format it speaks are the protocol's
(``bmi_sdk.protocol``, docs/protocol.md), shared with the host. Importing this
package loads neither the renderer nor the optics: the optical sources import
them when a scene is built, ``FirmwareDevice`` when it looks up its lens.
"""

from .device import FirmwareDevice, lens_identity
from .endpoint import FirmwareServer, InProcessLink
from .faults import Fault, FaultPlan
from .optical import ProceduralOpticalSource, RenderedScene
from .sources import (
                      DarkFrame,
                      FlatField,
                      InFocusImageStandIn,
                      IrradianceSource,
                      PolarChart,
                      make_source,
                      register_source,
                      source_names,
)

__all__ = [
    "FirmwareDevice", "lens_identity", "FirmwareServer", "InProcessLink",
    "Fault", "FaultPlan", "DarkFrame", "FlatField", "InFocusImageStandIn", "IrradianceSource", "PolarChart",
    "make_source", "register_source", "source_names", "RenderedScene", "ProceduralOpticalSource",
]
