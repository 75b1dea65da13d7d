"""profile_pose: one command for the tools, each tool's options its own."""
from __future__ import annotations

import pytest

from profile_pose_ros.tools import cli


def test_every_tool_is_reachable_and_names_itself(capsys) -> None:
    for name in cli.TOOLS:
        with pytest.raises(SystemExit) as done:
            cli.main([name, "--help"])
        assert done.value.code == 0
        assert f"usage: profile_pose {name}" in capsys.readouterr().out


def test_no_or_unknown_tool_is_refused_with_the_list(capsys) -> None:
    assert cli.main([]) == 2
    assert "experiment" in capsys.readouterr().out
    assert cli.main(["experimnet"]) == 2
    err = capsys.readouterr().err
    assert "no tool 'experimnet'" in err and "profiler-check" in err
    assert cli.main(["--help"]) == 0
