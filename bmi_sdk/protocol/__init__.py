"""The BMI camera protocol (docs/protocol.md): what a camera and a host say to each other.

Both ends import it: the simulated firmware (``firmware_sim``) and the host
camera API (``devices``). It sits below both and imports neither, nor the
optics or the renderer, so a host talking to a real camera loads only this
and numpy.

* ``registers`` — the register map: addresses, units, ranges, access, the
  ROI registers, result codes (``RegError``), STATUS bits, test patterns;
* ``wire`` — messages and their envelope, the frame header, CFA codes, RAW12
  packing, CRC32, the timing both ends rely on, the model name and the form
  of a TCP camera's URI.
"""
