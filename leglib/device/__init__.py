"""An ODrive, real or virtual, and setting it up for the leg.

:mod:`~leglib.device.session` connects (:func:`connect`) and gives a :class:`Device`: the
object tree, logical property names across firmware 0.5.x, the clock, the error flags and
fail-safe idling; :mod:`~leglib.device.setup` configures, calibrates, zeroes and stores
gains (Listings 7.1, 7.2), each only where the board needs it; :mod:`~leglib.device.bench`
keeps what a run did on the leg and its bench time, estimates a run beforehand and limits
it; :mod:`~leglib.device.usb` finds the real board;
:mod:`~leglib.device.virtual` is the virtual ODrive v3.6 (the twin behind the firmware's
behaviour and its wire).
"""
