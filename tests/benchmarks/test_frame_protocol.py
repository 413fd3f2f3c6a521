"""`benchmarks.frame_protocol`: the same frames timed under the suite's protocol (G-buffer made right
before each frame) and back to back render the same images, and every kind gets both medians."""


def test_frame_protocol_times_both_protocols_on_the_same_images():
    from benchmarks import frame_protocol

    out = frame_protocol.main(["--method", "sh_prt", "--scene", "sphere_plane", "--size", "test",
                               "--kinds", "V", "L", "--frames", "2", "--repeat", "1", "--threads", "1"])
    assert set(out["kinds"]) == {"V", "L"}
    for r in out["kinds"].values():
        assert r["same_image"] is True
        assert r["suite"] > 0 and r["b2b"] > 0
        assert r["cost"] is not None and r["cost"][0] > 0
