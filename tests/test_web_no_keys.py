"""No key in any URL: the browser code and the tools that print or open page addresses.

The browser signs in once (the key POSTed to ``/api/v1/session``) and then carries only an
HttpOnly cookie; this scans the files that build page addresses, share links, exports and
downloads for anything that would put a key into a URL or into script-readable storage. The
Chromium side (address bar, share link, exported file) is
``tests/test_web_browser.py::test_address_bar_share_link_and_export_never_hold_the_key``.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "cranetwin"

#: what would carry a key into an address, a request header set by page scripts, or storage
FORBIDDEN = re.compile(
    r"[?&]key=|searchParams\.(set|append)\(\s*[\"']key[\"']|[\"']x-api-key[\"']\s*:"
    r"|localStorage\.setItem|sessionStorage|Authorization[\"']?\s*:", re.IGNORECASE)

#: Python files that print or open page addresses
PY_FILES = [SRC / "bench" / "web.py", SRC / "cli" / "web.py", SRC / "cli" / "fleetdemo.py",
            SRC / "demo.py", SRC / "viz" / "export.py"]


def _code_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, line) without comment lines (``//``, ``#``, ``*``)."""
    out = []
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        stripped = line.strip()
        if stripped.startswith(("//", "#", "*", "/*")):
            continue
        out.append((i, line))
    return out


def _web_files() -> list[Path]:
    web = ROOT / "web"
    return sorted(p for p in web.rglob("*") if p.suffix in (".js", ".html")
                  and "vendor" not in p.parts and "lib" not in p.parts)  # third-party


@pytest.mark.timeout(30)
def test_the_rule_finds_what_it_forbids() -> None:
    for bad in ('url.searchParams.set("key", k)', "fetch(`/x?key=${key}`)",
                'headers: { "X-API-Key": key }', "localStorage.setItem('k', key)",
                'f"{url}/machines/a?mode=live&key={key}"'):
        assert FORBIDDEN.search(bad), bad
    for good in ('url.searchParams.get("key")', 'url.searchParams.delete("key")',
                 "const sort = { key: 'status' }"):
        assert not FORBIDDEN.search(good), good


@pytest.mark.timeout(30)
def test_browser_code_never_puts_a_key_in_a_url_or_storage() -> None:
    files = _web_files()
    assert len(files) >= 8, files  # the pages and modules are really scanned
    hits = [f"{p.relative_to(ROOT)}:{i}: {line.strip()}" for p in files
            for i, line in _code_lines(p) if FORBIDDEN.search(line)]
    assert not hits, "\n".join(hits)


@pytest.mark.timeout(30)
def test_tools_print_and_open_pages_without_keys() -> None:
    hits = []
    for p in PY_FILES:
        for i, line in _code_lines(p):
            # API calls from Python may send X-API-Key headers; page addresses never carry keys
            if re.search(r"[?&]key=", line):
                hits.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not hits, "\n".join(hits)
