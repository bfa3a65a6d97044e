"""The kernel cache folder: NUMBA_CACHE_DIR when set, else under the user's cache home."""

import os
from pathlib import Path

from endo_io.kernel_cache import kernel_cache_dir, use_kernel_cache


def test_numba_cache_dir_is_respected(monkeypatch, tmp_path):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "mine"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert kernel_cache_dir() == tmp_path / "mine"
    assert use_kernel_cache() == tmp_path / "mine"
    assert os.environ["NUMBA_CACHE_DIR"] == str(tmp_path / "mine")


def test_default_is_under_the_cache_home_not_the_source_tree(monkeypatch, tmp_path):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert kernel_cache_dir() == tmp_path / "xdg" / "endo3d" / "numba"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert kernel_cache_dir() == tmp_path / "home" / ".cache" / "endo3d" / "numba"
    folder = use_kernel_cache()
    assert os.environ["NUMBA_CACHE_DIR"] == str(folder)
    source_tree = Path(__file__).resolve().parents[2]
    assert source_tree not in folder.parents
