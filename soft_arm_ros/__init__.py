"""ROS 2 plumbing shared by every soft_arm node, controller and drivers alike.

- :mod:`.contract`: topic names, message types, QoS, the ``arm_base`` frame;
- :mod:`.conversions`: messages to and from numpy;
- :mod:`.parameters`: a node's validated parameters (package config files + its own values);
- :mod:`.runtime`: the executor and the process life of a node (signals, clean exit, status 2 on a
  bad parameter);
- :mod:`.backlog`: a subscription whose callback can outlast its messages' period, kept from
  building a backlog;
- :mod:`.lifecycle`: managed (lifecycle) nodes for the rig's hardware drivers;
- :mod:`.hardware_lock`: the lock a lifecycle node's hardware is used under, naming its holder;
- :mod:`.localhost_discovery`: room on a domain for a run's processes under localhost discovery.

It sits below both ``soft_arm_control`` and ``soft_arm_drivers`` and imports neither; the ROS-free
parameter engine it builds on is :mod:`soft_arm_model.parameters`.
"""
