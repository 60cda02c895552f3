"""The simulated rig that stands in for the hardware: the plant and its sensors
(:mod:`.simulated_rig`, parameters in :mod:`.plant_config`), the ``simulator`` node, and the
emulated hardware (:mod:`.can_emulator`, :mod:`.natnet_emulator`, the ``emulated_rig`` node).
Only this room reads ``plant.yaml``."""
