"""Experiments, on any ODrive (the real leg or the twin): the step and its sweep
(Listing 7.4), torque playback and the friction experiment (Listing 7.3, thesis 5.2), the
return to rest. Each arms the motors under the watchdog and leaves both axes IDLE however it
ends.
"""
