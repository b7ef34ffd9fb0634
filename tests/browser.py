"""A page loaded in a real headless browser (Debian's chromium, which ``make setup`` installs): how many of
its images there are and how many failed to decode, as a user opening it would find them."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path


def images_in_browser(page: Path, probe_dir: Path) -> tuple[int, int, str]:
    """(images, broken, the browser's stderr) of ``page`` once everything has loaded: the page plus a
    script that writes the two counts into its title, dumped by chromium --headless."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    assert browser, "chromium is not installed: `make setup` installs it (Debian package chromium)"
    probe = probe_dir / "probe.html"
    probe.write_text(
        page.read_text().replace(
            "</body>",
            "<script>window.addEventListener('load', () => { const im = [...document.images];"
            "document.title = 'images ' + im.length + ' broken ' +"
            " im.filter(i => !i.complete || i.naturalWidth === 0).length; });</script></body>",
        )
    )
    out = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=5000", "--dump-dom",
         probe.as_uri()],
        capture_output=True,
        text=True,
        timeout=120,
    )  # fmt: skip
    title = out.stdout.split("<title>", 1)[1].split("</title>", 1)[0]
    _, images, _, broken = title.split()
    return int(images), int(broken), out.stderr[-2000:]
