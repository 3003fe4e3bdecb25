"""sim_learner/sitl.py without booting SITL: what it would start with (the SITL runs themselves are in
tests/integration/test_sitl.py and tests/integration/test_demo_sitl.py, marked ``sitl``)."""

from __future__ import annotations

from sim_learner.sitl import Sitl


def test_a_relative_binary_and_its_default_params_are_found_from_sitls_own_directory(tmp_path, monkeypatch) -> None:
    """SITL runs in a directory of its own: a binary named relative to the caller's (``scmbridge demo --sitl
    ../sitl/ardurover``) was not found there (FileNotFoundError), nor its default_params."""
    (tmp_path / "sitl").mkdir()
    (tmp_path / "sitl" / "ardurover").write_bytes(b"")
    (tmp_path / "work").mkdir()
    monkeypatch.chdir(tmp_path / "work")
    sitl = Sitl("../sitl/ardurover", model="rover-skid")
    assert sitl.binary == tmp_path / "sitl" / "ardurover" and sitl.binary.is_absolute()
    assert all(p.is_absolute() for p in sitl.defaults())
    assert sitl.defaults()[0] == tmp_path / "sitl" / "default_params" / "rover.parm"
