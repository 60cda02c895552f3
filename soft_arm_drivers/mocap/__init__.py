"""The rig's motion capture: the NatNet codec (:mod:`.natnet`), the bridge's configuration and
calibration (``config/mocap.yaml``), the ROS-free bridge core (:mod:`.mocap_bridge`) and its node."""
