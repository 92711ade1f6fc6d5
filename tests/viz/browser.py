"""Headless Chromium for the viewer tests: WebGL through the SwiftShader software rasteriser."""

from __future__ import annotations

import html
import json
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
INSTALL_HINT = "chromium not installed: apt-get install chromium"
FLAGS = (
    "--headless=new",
    "--no-sandbox",  # tests often run as root in containers, where the sandbox refuses to start
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
    "--hide-scrollbars",
    "--no-first-run",
    "--disable-extensions",
    "--mute-audio",
    "--enable-logging=stderr",
    "--v=0",
)


def find_chromium() -> str | None:
    """Path of a Chromium (or Chrome) executable on PATH, or None."""
    return next((path for name in CHROMIUM_NAMES if (path := shutil.which(name))), None)


@dataclass
class BrowserRun:
    stdout: str
    log: str

    def console_errors(self) -> list[str]:
        """Page console lines that report an error (uncaught exceptions and console.error text)."""
        lines = [line for line in self.log.splitlines() if ":CONSOLE" in line]
        return [line for line in lines if re.search(r"uncaught|error", line, re.I)]

    def body_attributes(self) -> str:
        match = re.search(r"<body([^>]*)>", self.stdout)
        return match.group(1) if match else ""

    def checksums(self) -> dict:
        """The JSON the page writes into ``<pre id="t3-checksums">``."""
        match = re.search(r'<pre id="t3-checksums"[^>]*>(.*?)</pre>', self.stdout, re.S)
        assert match and match.group(1), "the page wrote no checksums"
        return json.loads(match.group(1))


def file_url(path: Path, fragment: str = "") -> str:
    return path.resolve().as_uri() + (f"#{fragment}" if fragment else "")


def run_chromium(url: str, *, screenshot: Path | None = None, dump_dom: bool = False,
                 size: tuple[int, int] = (1280, 720), budget_ms: int = 20000, timeout: float = 90,
                 flags: tuple[str, ...] = ()) -> BrowserRun:
    """Load ``url`` headless; write a PNG screenshot and/or return the serialised DOM (stdout).

    ``--virtual-time-budget`` lets the page run until it is idle or the budget is spent, so
    the decode and the first frame finish before the screenshot or the DOM dump. ``flags``:
    more Chromium switches.
    """
    chromium = find_chromium()
    assert chromium, INSTALL_HINT
    with tempfile.TemporaryDirectory(prefix="t3-chromium-") as profile:
        cmd = [chromium, *FLAGS, f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
               f"--virtual-time-budget={budget_ms}", *flags]
        cmd += [f"--screenshot={screenshot}"] if screenshot else []
        cmd += ["--dump-dom"] if dump_dom else []
        done = subprocess.run([*cmd, url], capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"chromium exited with {done.returncode}:\n{done.stderr[-3000:]}"
    return BrowserRun(done.stdout, done.stderr)


# Loads the page in an iframe, makes its lazy images load now, waits for each to load or fail
# (pending loads hold virtual time; an image's decode() does not) and reports what it saw.
_RESOURCES_PAGE = """<!DOCTYPE html>
<html><body><iframe src="{url}" style="width: 1280px; height: 720px"></iframe><pre id="t3-resources"></pre>
<script>
const settled = (img) => img.complete ? Promise.resolve() : new Promise((done) => {{
  img.addEventListener("load", done);
  img.addEventListener("error", done);
}});
document.querySelector("iframe").addEventListener("load", async (event) => {{
  const page = event.target.contentDocument;
  const images = [...page.images];
  images.forEach((img) => {{ img.loading = "eager"; }});
  await Promise.all(images.map(settled));
  document.getElementById("t3-resources").textContent = JSON.stringify({{
    images: images.map((img) => ({{src: img.src, width: img.naturalWidth}})),
    links: [...page.links].map((a) => a.href),
  }});
}});
</script></body></html>
"""


def page_resources(page: Path) -> dict:
    """What Chromium makes of the static ``page``: ``{"images": [{"src", "width"}], "links": [url]}``,
    each URL resolved by the browser against the page, ``width`` the image's natural width
    (0: not loaded)."""
    with tempfile.TemporaryDirectory(prefix="t3-resources-") as folder:
        probe = Path(folder) / "probe.html"
        probe.write_text(_RESOURCES_PAGE.format(url=file_url(page)), encoding="utf-8")
        # file:// pages may read each other's documents only with this switch
        run = run_chromium(file_url(probe), dump_dom=True, flags=("--allow-file-access-from-files",))
    match = re.search(r'<pre id="t3-resources"[^>]*>(.*?)</pre>', run.stdout, re.S)
    assert match and match.group(1), f"the probe page reported nothing:\n{run.log[-3000:]}"
    return json.loads(html.unescape(match.group(1)))
