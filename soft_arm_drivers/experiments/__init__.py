"""The paper's experiments: the task runner (goals and metrics), the ROS-free closed-loop harness
(``soft-arm-harness``), the ``soft-arm-experiment`` command (composed lockstep, one process per node,
emulated hardware), and the figures read back from the bag."""
