"""Where numba keeps the compiled kernels: numba's own choice where it works, a temporary directory
where it would refuse to define them (a read-only install run without a writable home)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numba
import pytest

from slam6d import kernel_cache


@pytest.fixture
def unwritable(tmp_path: Path) -> Path:
    """A directory path no one can create, root included: its parent is a regular file."""
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    return blocker / "cache"


def test_the_users_numba_cache_dir_always_wins(unwritable: Path) -> None:
    environ = {"NUMBA_CACHE_DIR": "/somewhere", "HOME": str(unwritable)}
    assert kernel_cache.kernel_cache_dir(environ, package_cache=unwritable) is None


def test_numbas_own_choice_is_kept_where_it_can_write(tmp_path: Path, unwritable: Path) -> None:
    # beside the sources (an editable or virtualenv install)
    assert kernel_cache.kernel_cache_dir({"HOME": str(unwritable)}, package_cache=tmp_path / "__pycache__") is None
    # a read-only install: numba falls back to its user cache, $XDG_CACHE_HOME/numba or ~/.cache/numba
    assert kernel_cache.kernel_cache_dir({"HOME": str(tmp_path)}, package_cache=unwritable) is None
    assert kernel_cache.numba_user_cache({"HOME": str(tmp_path)}) == tmp_path / ".cache" / "numba"
    environ = {"HOME": str(unwritable), "XDG_CACHE_HOME": str(tmp_path / "xdg")}
    assert kernel_cache.numba_user_cache(environ) == tmp_path / "xdg" / "numba"
    assert kernel_cache.kernel_cache_dir(environ, package_cache=unwritable) is None


def test_a_temporary_directory_where_numba_could_write_nowhere(unwritable: Path) -> None:
    chosen = kernel_cache.kernel_cache_dir({"HOME": str(unwritable)}, package_cache=unwritable)
    assert chosen is not None
    assert chosen.parent == Path(tempfile.gettempdir())
    assert chosen.name.startswith("slam6d-numba-cache-")


def test_use_kernel_cache_reaches_a_numba_already_loaded(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(numba.config, "CACHE_DIR", numba.config.CACHE_DIR)
    monkeypatch.setenv("NUMBA_CACHE_DIR", "")  # restored (unset) after the test
    kernel_cache.use_kernel_cache(tmp_path)
    assert str(tmp_path) == numba.config.CACHE_DIR

    @numba.njit(cache=True)
    def twice(x: float) -> float:
        return 2.0 * x

    assert twice(1.5) == 3.0
    assert any(tmp_path.rglob("*.nbi"))  # the kernel's cache index went there
