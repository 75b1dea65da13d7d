"""Every decoder and parser of outside input, fuzzed (a short budget; `profile_pose fuzz` runs 100,000 per
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


def test_a_rogue_correction_of_1e300_m_per_s_is_clamped_not_an_overflow() -> None:
    """Found by the node fuzzer: the bridge's socket thread raised OverflowError turning it into units."""
    from profile_pose_ros.core.wire import motoplus_protocol as mp
    from profile_pose_ros.devices.motoplus_client import MotoPlusClient, SessionLimits

    limits = SessionLimits()
    client = MotoPlusClient("127.0.0.1", 9, limits, lambda now: None, lambda state, t: None)
    assert client.units_for([1e300, -1e300, 0.0, 1e300, 0.0, 0.0]) == (
        tuple(int(s * k) for s, k in zip((1, -1, 0, 1, 0, 0), mp.metres_to_units(limits.max_step))))
