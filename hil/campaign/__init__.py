"""Campaigns: many runs of ``hil sim`` or of a fusion rerun, as tasks on a Dask cluster.

``spec`` reads and checks a campaign (TOML), ``runs`` derives its runs (seeds from the
campaign's seed and each replicate's index), ``execute`` is what a worker does with one run,
``driver`` sends the runs to Dask and journals what comes back, ``results`` is the journal and
table on disk, ``report`` the HTML page over a campaign (and the comparison of two). The user's
guide is ``docs/campaigns.md``.
"""
