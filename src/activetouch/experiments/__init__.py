"""Episodes, metrics, result files and figures.

* :mod:`activetouch.experiments.metrics` - NLL (RUMI Eq. 36), APC (Eq. 33), ADI, pose errors, Wilson interval.
* :mod:`activetouch.experiments.runner` - the closed loop of RUMI Algorithm 1 for any registered method + task.
* :mod:`activetouch.experiments.records` - result files written as an episode goes (``steps.csv``, ``summary.json``).
* :mod:`activetouch.experiments.stop_rule` - RUMI's APC stop (Eq. 33) replayed at other beta_t from ``--no-terminate``
  episodes.
* :mod:`activetouch.experiments.plots` - figures like the papers' (belief particles, information field, NLL curves).
"""
