"""`credit bench env --vs-smax`: which SMAX map each skirmish map is compared with."""

from cluster.bench.env import smax_map_for


def test_smacv2_style_scenarios_pair_with_smaxs_randomised_maps():
    assert smax_map_for("skirmish/protoss_5_vs_5") == "smacv2_5_units"
    assert smax_map_for("skirmish/zerg_10_vs_10") == "smacv2_10_units"
    assert smax_map_for("skirmish/terran_20_vs_20") == "smacv2_20_units"
    assert smax_map_for("skirmish/2s3z") == "2s3z"
    assert smax_map_for("skirmish/protoss_10_vs_11") == "protoss_10_vs_11"  # no SMAX pair
