"""``pidg bench render``'s feature sweep, including its case of features read on a few tiles only."""
from pidg.bench.render import RenderBenchCase, RenderBenchConfig, _centre_tiles, _feature_sweep
from pidg.render.projection import tiles_touched


def test_centre_tiles_are_a_centred_square_of_the_share_asked():
    pixels = _centre_tiles(256, 0.05)  # 256 tiles of 16x16: 12.8 asked -> a 4 x 4 square
    touched = tiles_touched(pixels, 16)
    assert int(touched.sum()) == 16 and bool(touched[6:10, 6:10].all())
    assert int(pixels.sum()) == 16 * 256  # whole tiles
    assert int(tiles_touched(_centre_tiles(40, 0.001), 16).sum()) == 1  # at least one tile


def test_the_feature_sweep_times_every_channel_count_and_the_few_tiles_case():
    lines = []
    config = RenderBenchConfig(cases=[RenderBenchCase("b", 300, 64)], repeats=1, feature_channels=(0, 4))
    sweep = _feature_sweep(config, lines.append)
    assert [(row["channels"], row["tile_share"] == 1) for row in sweep] == [(0, True), (4, True), (4, False)]
    assert 0 < sweep[-1]["tile_share"] < 1 and all(row["forward_backward_ms"] > 0 for row in sweep)
    assert "C=4 on " in lines[-1] and "% of the tiles" in lines[-1]
