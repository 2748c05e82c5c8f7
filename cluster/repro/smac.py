"""The value family and RDN on SMAC-like maps (IQL, VDN, QMIX, QMIX-nostate, RDN): learning
speed and stability against the reference numbers of results/smac/README.md.

The runs, logs, summary and plots are `cluster.repro.curves`'; this module names the
experiment's default maps, algorithms and the learner diagnostics it plots (Q-value scale and
TD error, the first things to look at when a value learner collapses).
"""

from __future__ import annotations

ENVS = ("skirmish/3m", "skirmish/8m")
ALGOS = ("iql", "vdn", "qmix", "qmix_ns", "rdn")
DIAGNOSTICS = (
    ("q_taken_mean", "mean Q of the taken actions (value family)"),
    ("loss_td", "TD loss (value family)"),
    ("q_tot_mean", "RDN critic value"),
    ("loss_critic", "RDN critic TD loss"),
)
PLOT_PREFIX = "smac"
