"""hw: control of the integrating-sphere multispectral instrument (filter wheels, shutter, lamp,
camera) over pyserial, and emulated devices that follow the vendors' protocols.

See ../shared/INSTRUMENT.md for the devices and protocols. This package never imports spherejax's
maths except to render frames for the simulated camera. The drivers arrive with the hw/ issue;
until then the package holds nothing but this description.
"""
