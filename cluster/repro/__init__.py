"""Reproductions of the dissertation's experiments, one module each, sharing curve, summary and
plot code (`curves`) and the fan-out of (algorithm, env) pairs over processes or a Ray cluster
(`fanout`)."""
