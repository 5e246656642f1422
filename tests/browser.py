"""A static report (index.html and its images) rendered in headless Chromium, checked as a reader would see it: every
image loaded, every table filled, none of the given error words in the text. Used by the demo's and the shift's
report tests; skips (fails in CI) when Chromium is missing."""

from __future__ import annotations

import pathlib
import re
import shutil
import subprocess
from collections.abc import Sequence

from tests.required import missing

CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def check_rendered_report(page: pathlib.Path, profile: pathlib.Path, min_images: int, min_tables: int,
                          bad_words: Sequence[str]) -> str:
    """Render ``page``; assert at least ``min_images`` images all loaded, at least ``min_tables`` tables none empty,
    and no word of ``bad_words``. Returns the page's text."""
    chromium = shutil.which("chromium")
    if chromium is None:
        missing("browser", "Debian chromium is not installed (scripts/setup.sh installs it when run as root)")
    dom = subprocess.run([chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--virtual-time-budget=10000",
                          "--dump-dom", page.as_uri()], capture_output=True, text=True, timeout=120).stdout
    body = re.search(r"<body([^>]*)>", dom)
    assert body, "Chromium returned no page"
    images = re.search(r'data-images="(\d+)"', body.group(1))
    broken = re.search(r'data-broken="([^"]*)"', body.group(1))
    assert images and int(images.group(1)) >= min_images, "the page's image check did not run or found too few images"
    assert broken is not None and broken.group(1) == "", f"images that did not load: {broken and broken.group(1)}"
    tables = re.findall(r"<table>(.*?)</table>", dom, flags=re.S)
    assert len(tables) >= min_tables
    for table in tables:
        assert table.count("<tr>") >= 2, f"an empty table: {table[:200]}"
    text = re.sub(r"<[^>]+>", " ", dom)
    for bad in bad_words:
        assert bad not in text, f"'{bad}' in the report"
    return text
