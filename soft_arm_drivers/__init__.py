"""The rig's hardware and its stand-ins, one room per concern:

- :mod:`.can`: the rig's motors: MIT-protocol codec, the CAN motor driver and its node;
- :mod:`.mocap`: the rig's motion capture: NatNet codec, the mocap bridge and its node;
- :mod:`.sim`: the simulated rig that stands in for both: the plant (the arm with its own
  parameters, ``plant.yaml``), encoders and mocap models, the simulator node, the CAN-motor and
  NatNet-server emulators and the emulated_rig node;
- :mod:`.recording`: the rosbag2 MCAP writer and the recorder node.

The experiments and campaigns run on them live above, in :mod:`soft_arm_experiments`.
"""
