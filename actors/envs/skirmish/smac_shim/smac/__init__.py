"""A stand-in for oxwhirl's `smac` package that runs on skirmish (no StarCraft II).

Only on the import path when you put its parent folder there (see
`actors.envs.skirmish.smac_shim_path()` and the skirmish README); nothing in `credit`
imports it.
"""
