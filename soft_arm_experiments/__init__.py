"""The lab's work on the arm, above the drivers: what is run on it and what is measured.

- the paper's experiments: the task runner (goals and metrics) and its node, the ROS-free
  closed-loop harness (``soft-arm-harness``), the ``soft-arm-experiment`` command (composed
  lockstep, one process per node, emulated hardware), lockstep scheduling and the figures read back
  from the bag;
- identification: the excitation and its node, the recorded identification run and
  ``soft-arm-identify``;
- :mod:`.campaigns`: many runs on Dask (``soft-arm-campaign``): sweeps, robustness over drawn
  plants, identification over drawn plants, and their reports;
- :mod:`.warmup`: every numba kernel of the stack compiled into its cache (``soft-arm-warmup``).

It may import the drivers, the controller, the ROS plumbing and the model; none of them imports it.
"""
