"""Metrics: the Prometheus exporters of actors and learner (`exporters`), their HTTP endpoint
(`http`), file service discovery (`discovery`), a real Prometheus (`prometheus`) and the loop's
counters (`loop_stats`)."""
