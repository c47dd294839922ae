"""Atomic writes: complete file or the old one, never a half-written file or a leftover temp."""

from __future__ import annotations

import os

import pytest

from railtraj.io.atomic import atomic_path, atomic_write


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_atomic_write_creates_parents_and_file(tmp_path):
    target = tmp_path / "a" / "b" / "out.csv"
    with atomic_write(target) as f:
        f.write("x,y\n1,2\n")
        assert not target.exists(), "target must not appear before the block ends"
        assert _leftovers(target.parent)[0].endswith(".part")
    assert target.read_text() == "x,y\n1,2\n"
    assert _leftovers(target.parent) == []


def test_atomic_write_failure_keeps_old_file_and_removes_temp(tmp_path):
    target = tmp_path / "out.csv"
    target.write_text("old\n")
    with pytest.raises(RuntimeError), atomic_write(target) as f:
        f.write("new, half written")
        raise RuntimeError("killed")
    assert target.read_text() == "old\n"
    assert _leftovers(tmp_path) == []


def test_atomic_write_binary_and_newlines(tmp_path):
    target = tmp_path / "out.bin"
    with atomic_write(target, "wb") as f:
        f.write(b"\x00\x01\r\n")
    assert target.read_bytes() == b"\x00\x01\r\n"
    with atomic_write(tmp_path / "t.txt") as f:
        f.write("a\nb\n")
    assert (tmp_path / "t.txt").read_bytes() == b"a\nb\n"


def test_atomic_write_rejects_read_modes(tmp_path):
    with pytest.raises(ValueError), atomic_write(tmp_path / "x", "r"):
        pass


def test_atomic_write_permissions_follow_umask(tmp_path):
    umask = os.umask(0)
    os.umask(umask)
    target = tmp_path / "out.csv"
    with atomic_write(target) as f:
        f.write("x")
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask


def test_atomic_path_keeps_suffix_and_renames(tmp_path):
    target = tmp_path / "sub" / "tile.laz"
    with atomic_path(target) as tmp:
        assert tmp.parent == target.parent
        assert tmp.name.startswith(".") and tmp.name.endswith(".tmp.laz")
        tmp.write_bytes(b"data")
    assert target.read_bytes() == b"data"
    assert _leftovers(target.parent) == []


def test_atomic_path_failure_deletes_temp(tmp_path):
    target = tmp_path / "tile.laz"
    with pytest.raises(OSError), atomic_path(target) as tmp:
        tmp.write_bytes(b"partial")
        raise OSError("disk full")
    assert not target.exists()
    assert _leftovers(tmp_path) == []
