"""plotly.js is compressed once and then read from the cache folder: the same bytes either way, a cache of
another plotly.js is not used, and an unwritable cache folder only makes it slower."""

from __future__ import annotations

import base64
import gzip
from pathlib import Path

import pytest

from cell.analysis import view3d


@pytest.fixture
def fresh(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    monkeypatch.setenv("CELL_CACHE_DIR", str(tmp_path / "cache"))
    view3d.plotly_js_gzip_base64.cache_clear()
    yield tmp_path / "cache"
    view3d.plotly_js_gzip_base64.cache_clear()


def test_the_cached_script_is_the_compressed_plotly_js(fresh: Path) -> None:
    from plotly.offline import get_plotlyjs

    first = view3d.plotly_js_gzip_base64()
    (cached,) = fresh.glob("plotly-*.js.gz.b64")
    assert cached.read_text() == first
    assert gzip.decompress(base64.b64decode(first)).decode() == get_plotlyjs()
    cached.write_text("c2FtZQ==")  # a cache entry is what is used while plotly.js is the same ...
    view3d.plotly_js_gzip_base64.cache_clear()
    assert view3d.plotly_js_gzip_base64() == "c2FtZQ=="
    cached.rename(fresh / "plotly-0123456789abcdef0123.js.gz.b64")  # ... and one of another is not
    view3d.plotly_js_gzip_base64.cache_clear()
    assert view3d.plotly_js_gzip_base64() == first


def test_an_unwritable_cache_only_costs_time(fresh: Path) -> None:
    fresh.parent.mkdir(exist_ok=True)
    fresh.write_text("a file where the folder should be")
    packed = view3d.plotly_js_gzip_base64()
    assert gzip.decompress(base64.b64decode(packed))[:100] and fresh.is_file()
