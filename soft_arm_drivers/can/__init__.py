"""The rig's direct-drive motors on CAN: the MIT-protocol codec (:mod:`.mit_protocol`), the driver's
configuration (``config/rig.yaml``) and ROS-free core (:mod:`.motor_driver`) and its node."""
