"""Generated bane_vs_bane variants `skirmish/bane_z<N>` (the seed's redundancy maps, any N)."""

import dataclasses

import numpy as np
import pytest

from actors.envs.base import EnvError
from actors.envs.registry import env_info, get_spec, make_vec_env
from actors.envs.skirmish.maps import bane_variant, builtin_map
from actors.envs.skirmish.spec import ordered_units


@pytest.mark.parametrize(
    "n, table_map", [(20, "bane_vs_bane"), (15, "bane_med"), (10, "bane_small")]
)
def test_generated_variants_are_the_seeds_maps(n, table_map):
    assert dataclasses.replace(bane_variant(n), name=table_map) == builtin_map(table_map)


def test_no_zerglings_keeps_the_banelings_at_their_point():
    z0, no_z = bane_variant(0), builtin_map("bane_no_z")
    assert z0.n_agents == no_z.n_agents == 4 and z0.enemies == no_z.enemies
    # SMAC's blob spawn around each group's point: bane_z0's at 8, bane_no_z's at 11.
    assert np.mean(z0.allies[0].positions, 0) == pytest.approx([8.2, 16.2], abs=0.3)
    assert np.mean(no_z.allies[0].positions, 0) == pytest.approx([11.2, 16.2], abs=0.3)
    assert env_info("skirmish/bane_z0").obs_shape == env_info("skirmish/bane_no_z").obs_shape


@pytest.mark.parametrize("n", [0, 5, 30])
def test_sizes_follow_the_number_of_zerglings(n):
    info = env_info(f"skirmish/bane_z{n}")
    agents = n + 4
    assert (info.n_agents, info.n_enemies, info.n_actions) == (agents, 24, 30)
    # SMAC's layout: 4 move flags, 24 enemies and agents - 1 allies of 7, own health + type
    assert info.obs_shape == 4 + 24 * 7 + (agents - 1) * 7 + 3
    assert info.state_shape == agents * 6 + 24 * 5 + agents * 30


@pytest.mark.parametrize("n", [30, 64])
def test_a_big_blob_of_zerglings_spawns_around_its_point_clear_of_the_banelings(n):
    names, pos = ordered_units(bane_variant(n), "allies")
    banes = pos[[i for i, t in enumerate(names) if t == "baneling"]]
    lings = pos[[i for i, t in enumerate(names) if t == "zergling"]]
    assert lings.mean(0) == pytest.approx([11.0, 16.0], abs=0.6)
    assert banes.mean(0) == pytest.approx([8.0, 16.0], abs=1.2)  # pushed back by 64
    gaps = np.linalg.norm(lings[:, None] - banes[None], axis=-1)
    assert gaps.min() >= 2 * 0.375 - 1e-6  # SC2 places each unit on a free spot


def test_a_generated_variant_plays_like_any_env():
    venv = make_vec_env("skirmish/bane_z5", 2, seed=0)
    venv.reset()
    rng = np.random.default_rng(0)
    for _ in range(20):
        avail = venv.get_avail_actions().astype(bool)
        acts = np.array([[rng.choice(np.flatnonzero(row)) for row in env] for env in avail])
        venv.step(acts, np.ones(2, bool))
    assert get_spec("skirmish/bane_z5").id == "skirmish/bane_z5"


@pytest.mark.parametrize("env_id", ["skirmish/bane_z65", "skirmish/bane_zz", "skirmish/bane_z"])
def test_bad_variants_are_refused_with_the_valid_range(env_id):
    with pytest.raises(EnvError, match=r"bane_z<N>"):
        env_info(env_id)
