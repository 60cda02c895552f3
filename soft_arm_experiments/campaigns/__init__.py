"""Campaigns: many independent simulations of the arm (robustness over drawn plants, identification
across plants or recorded bags, sweeps over any parameter) run on Dask, resumable, with progress.

- :mod:`.engine`: the runs keyed by their specification, on a Dask cluster (an embedded
  ``LocalCluster`` or a scheduler's address), each record written as it arrives;
- :mod:`.plants`: the casting tolerances and the plants drawn within them;
- :mod:`.runs`: what one run is (the functions the workers call);
- :mod:`.report`: the summary table and the distribution plots of a campaign's records;
- :mod:`.cli`: ``soft-arm-campaign``.
"""
