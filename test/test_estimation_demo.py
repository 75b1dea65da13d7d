"""The README's main job, end to end in its quick mode: the node runs as its own process."""
import json
import subprocess
import sys
from pathlib import Path


def test_quick_demo_passes_its_checks(tmp_path):
    exe = Path(sys.executable).parent / "profile_pose"
    result = subprocess.run([str(exe), "demo", "--quick", "--out", str(tmp_path)], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "[FAIL]" not in result.stdout and result.stdout.count("[PASS]") == 4
    (report,) = tmp_path.glob("*/estimation_demo.json")
    data = json.loads(report.read_text())
    assert data["node_noise-free"]["missing"] == 0
    assert data["noise_free"]["worst"]["ref_pos"] < 1e-9
