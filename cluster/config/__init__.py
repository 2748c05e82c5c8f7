"""Typed configuration: the loader (`schema`), the training run's dataclasses (`train`) and the
shipped YAML layers (`layers/`, package data)."""
