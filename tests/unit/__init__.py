"""Unit tests on a fake clock (tests/unit/conftest.py), no sleeps."""
