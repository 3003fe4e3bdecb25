"""``scmbridge keys mavlink --passphrase``: the key MAVProxy's ``signing setup PASSPHRASE`` makes of the same passphrase
(drivers/mavlink/signing.py)."""

from __future__ import annotations

import hashlib
import importlib.util
import subprocess
import sys

import pytest

from bridge.core.auth import load_key
from drivers.mavlink.signing import passphrase_key, signing_timestamp


def test_the_key_is_the_passphrases_sha256() -> None:
    # FIPS 180-2's "abc" vector: the digest itself, not our code computing it twice
    assert passphrase_key("abc").hex() == "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    assert passphrase_key("correct-horse") == hashlib.sha256(b"correct-horse").digest()


@pytest.mark.skipif(importlib.util.find_spec("MAVProxy") is None, reason="MAVProxy is not installed (dev lock)")
def test_the_key_is_mavproxys_for_the_same_passphrase() -> None:
    from MAVProxy.modules.mavproxy_signing import SigningModule

    for phrase in ("correct-horse-battery-staple", "x", "lab_rover_1!#%"):
        assert passphrase_key(phrase) == SigningModule.passphrase_to_key(None, phrase)


@pytest.mark.parametrize("phrase", ["", "motdepassé", "two words", "tab\there"])
def test_a_passphrase_mavproxy_cannot_take_is_refused(phrase: str) -> None:
    with pytest.raises(ValueError):
        passphrase_key(phrase)


def test_signing_timestamp_counts_10us_from_2015() -> None:
    assert signing_timestamp(1420070400.0) == 0
    assert signing_timestamp(1420070401.5) == 150_000


def test_keys_mavlink_passphrase_writes_that_key(tmp_path) -> None:
    out = tmp_path / "k"
    r = subprocess.run([sys.executable, "-m", "bridge", "keys", "mavlink", "--robot", "r1", "--out", str(out),
                        "--passphrase", "-"], input="correct-horse\n", capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert load_key(out, "mavlink") == hashlib.sha256(b"correct-horse").digest()
    assert oct(out.stat().st_mode & 0o777) == "0o600"
    bad = subprocess.run([sys.executable, "-m", "bridge", "keys", "mavlink", "--robot", "r1", "--out",
                          str(tmp_path / "j"), "--passphrase", "é"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "ASCII" in bad.stderr and not (tmp_path / "j").exists(), bad.stderr
    no_driver = subprocess.run([sys.executable, "-m", "bridge", "keys", "mavlink", "--robot", "r1", "--out",
                                str(tmp_path / "i"), "--install"], capture_output=True, text=True, timeout=60)
    assert no_driver.returncode == 2 and "--driver" in no_driver.stderr, no_driver.stderr
