"""The operating-point benchmark runs on the current code and its two ways agree (it raises when they do not)."""

from benchmarks.bench_operating_point import export_points, main


def test_the_bench_times_both_ways_on_the_export_configs_grid(capsys):
    assert len(export_points()) == 13 * 13 * 5 * 8   # conf/export: 13 thresholds a class, 5 x 8 minimum sides
    main(["--images", "3", "--boxes", "6", "--rounds", "1"])
    out = capsys.readouterr().out
    assert "6760 operating points x 3 images" in out and "speed-up:" in out
