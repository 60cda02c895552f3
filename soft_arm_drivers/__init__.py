"""Drivers of the rig and their stand-ins (simulator, CAN motors, motion capture, recorder)."""
