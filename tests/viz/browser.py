"""Headless Chromium for the viewer tests: WebGL through the SwiftShader software rasteriser."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import tempfile
import time
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
    seconds: float

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
                 size: tuple[int, int] = (1280, 720), budget_ms: int = 20000, timeout: float = 90) -> BrowserRun:
    """Load ``url`` headless; write a PNG screenshot and/or return the serialised DOM (stdout).

    ``--virtual-time-budget`` lets the page run until it is idle or the budget is spent, so
    the decode and the first frame finish before the screenshot or the DOM dump.
    """
    chromium = find_chromium()
    assert chromium, INSTALL_HINT
    with tempfile.TemporaryDirectory(prefix="t3-chromium-") as profile:
        cmd = [chromium, *FLAGS, f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
               f"--virtual-time-budget={budget_ms}"]
        cmd += [f"--screenshot={screenshot}"] if screenshot else []
        cmd += ["--dump-dom"] if dump_dom else []
        start = time.perf_counter()
        done = subprocess.run([*cmd, url], capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"chromium exited with {done.returncode}:\n{done.stderr[-3000:]}"
    return BrowserRun(done.stdout, done.stderr, time.perf_counter() - start)
