"""Every decoder and parser of outside input, fuzzed (a short budget; `profile_pose_fuzz` runs 100,000 per
target): only the documented error type may escape."""
from profile_pose_ros.tools import c_codec
from profile_pose_ros.tools.fuzz import fuzz


def test_no_decoder_raises_anything_but_its_documented_error() -> None:
    results = fuzz(2000, seed=7)
    assert len(results) == 9 + c_codec.available()  # the C codec's differential target needs a compiler
    for r in results:
        assert r["unexpected"] == 0, (r["target"], r["examples"])
        assert r["accepted"] > 0 and r["rejected"] > 0, r  # the mutations reach both outcomes
