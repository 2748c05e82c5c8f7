"""Reproductions of the seed's experiments, one module each, sharing curve, summary and plot code
(`curves`) and the fan-out of (algorithm, env) pairs over processes or a Ray cluster (`fanout`)."""
