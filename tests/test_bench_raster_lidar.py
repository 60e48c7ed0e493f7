"""``omnire bench raster --lidar``: a small real run writes its JSON and table; a malformed
beam grid is a one-line error naming the option."""
import json

from hostile import run_case


def test_bench_raster_lidar_writes_json(tmp_path, capsys):
    out = tmp_path / "lidar.json"
    code, text = run_case("bench raster --lidar, small", [
        "bench", "raster", "--lidar", "--rasterizers", "torch", "--gaussians", "500", "--lidar-rays", "8x90",
        "--repeats", "1", "--warmup", "0", "--threads", "1", "--output", str(out)], capsys, [], expect_exit=0,
        needles=("rasterize_lidar on cpu", "8x90"), surface="bench")
    result = json.loads(out.read_text())
    assert result["lidar"] is True
    (row,) = result["results"]
    assert row["rasterizer"] == "torch" and (row["height"], row["width"]) == (8, 90)
    assert row["forward_ms"] > 0 and row["backward_ms"] > 0


def test_bench_raster_malformed_grid_is_one_line(tmp_path, capsys):
    run_case("bench raster --lidar-rays 64by1800", [
        "bench", "raster", "--lidar", "--rasterizers", "torch", "--lidar-rays", "64by1800",
        "--output", str(tmp_path / "x.json")], capsys, [], expect_exit=2,
        needles=("--lidar-rays '64by1800'", "HEIGHTxWIDTH"), surface="bench")
    assert not (tmp_path / "x.json").exists()
