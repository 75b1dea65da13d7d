"""Every decoder and parser of outside input, fuzzed (a short budget; `profile_pose_fuzz` runs 100,000 per
target): only the documented error type may escape; and decoded values through the nodes' logic, where no
motion the raw values forbid may come out (the node targets must also catch nodes with a check removed)."""
import pytest

from profile_pose_ros.nodes import motoplus_bridge, pd_compensator
from profile_pose_ros.tools import c_codec
from profile_pose_ros.tools.fuzz import fuzz

POSES, CORRECTIONS = "poses through pd_compensator and motoplus_bridge", "corrections through motoplus_bridge"


def test_no_decoder_raises_anything_but_its_documented_error() -> None:
    results = fuzz(2000, seed=7)
    assert len(results) == 12 + c_codec.available()  # the C codec's differential target needs a compiler
    for r in results:
        assert r["unexpected"] == 0, (r["target"], r["examples"])
        assert r["accepted"] > 0 and r["rejected"] > 0, r  # the mutations reach both outcomes


@pytest.mark.parametrize("module, check, target", [(pd_compensator, "unit_quaternion", POSES),
                                                   (pd_compensator, "stamp_age_ok", POSES),
                                                   (motoplus_bridge, "stamp_age_ok", CORRECTIONS)])
def test_the_node_fuzzer_catches_a_node_without_one_of_its_checks(monkeypatch, module, check, target) -> None:
    monkeypatch.setattr(module, check, lambda *args: True)
    results = fuzz(2000, seed=7, names=[target])
    assert results[0]["unexpected"] > 0, results[0]
