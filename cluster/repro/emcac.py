"""Seed Table 5.2 and Figs. 5.10-5.13: the EM-CAC ablation (CAC, E-CAC, EM-CAC, COMA, QMIX).

The runs, logs, summary and plots are `cluster.repro.curves`'; this module names the
experiment's maps, algorithms and the learner diagnostics it plots.
"""

from __future__ import annotations

ENVS = ("skirmish/3s5z", "skirmish/MMM2", "skirmish/1c3s5z", "skirmish/2c_vs_64zg")
ALGOS = ("cac", "ecac", "emcac", "coma", "qmix")
DIAGNOSTICS = (("entropy", "policy entropy (nats)"), ("kl_masked_fraction", "KL-masked fraction"))
PLOT_PREFIX = "emcac"
