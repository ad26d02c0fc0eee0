"""Open a page in headless Chromium over the DevTools protocol on a pipe (standard library only).

Chromium started with ``--remote-debugging-pipe`` reads protocol commands from fd 3 and writes
replies and events to fd 4, each a JSON message ended by a NUL byte. No Python package and no
browser download is needed: only a Chromium binary (Debian's ``chromium``, found on PATH or
named by ``MMFLOW_CHROMIUM``).
"""
from __future__ import annotations

import base64
import json
import os
import select
import shutil
import subprocess
import tempfile
import time

CANDIDATES = ("chromium", "chromium-browser", "chromium-headless-shell", "headless_shell", "google-chrome",
              "google-chrome-stable", "chrome")
# Flags for a machine without a network and without a display (as root: no sandbox).
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--disable-quic",
         "--no-first-run", "--no-default-browser-check", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--disable-extensions", "--mute-audio")


def find_chromium():
    """Path of a Chromium binary, or None."""
    env = os.environ.get("MMFLOW_CHROMIUM")
    if env:
        return env if os.path.isfile(env) else shutil.which(env)
    for name in CANDIDATES:
        p = shutil.which(name)
        if p:
            return p
    return None


def install_chromium(timeout=900):
    """Path of a Chromium binary: one found, else Debian's ``chromium`` installed with apt-get.

    Returns ``(path, None)``, or ``(None, why)`` where no binary is found and none can be
    installed (not root, no apt-get, or the install failed: its last output line).
    """
    exe = find_chromium()
    if exe:
        return exe, None
    if not shutil.which("apt-get"):
        return None, "no Chromium binary and no apt-get to install Debian's `chromium` (or set MMFLOW_CHROMIUM)"
    if os.geteuid() != 0:
        return None, "no Chromium binary, and installing Debian's `chromium` needs root (or set MMFLOW_CHROMIUM)"
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    for cmd in (["apt-get", "install", "-y", "-q", "chromium"], ["apt-get", "update", "-q"],
                ["apt-get", "install", "-y", "-q", "chromium"]):  # an update only where the lists are stale
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
        except subprocess.TimeoutExpired:
            return None, f"`{' '.join(cmd)}` took over {timeout} s"
        if r.returncode == 0 and cmd[1] == "install":
            break
    exe = find_chromium()
    if exe is None:
        tail = (r.stderr or r.stdout).strip().splitlines()[-1:] or ["no output"]
        return None, f"Debian's `chromium` could not be installed: {tail[0]}"
    return exe, None


def dump_dom(exe, url, timeout=60.0):
    """The DOM of ``url`` once loaded, as ``chromium --dump-dom`` prints it (serialized HTML)."""
    with tempfile.TemporaryDirectory(prefix="mmflow-chromium-") as profile:
        r = subprocess.run([exe, *FLAGS, f"--user-data-dir={profile}", "--dump-dom", url], capture_output=True,
                           text=True, timeout=timeout, stdin=subprocess.DEVNULL)
    if r.returncode != 0:
        raise RuntimeError(f"chromium --dump-dom {url}: exit {r.returncode}: {r.stderr[-500:]}")
    return r.stdout


class Chromium:
    """A headless Chromium attached to one page, driven over the DevTools pipe."""

    def __init__(self, exe, timeout=60.0, width=1280, height=2000):
        self.timeout = timeout
        self.profile = tempfile.mkdtemp(prefix="mmflow-chromium-")
        cmd_r, self._cmd_w = os.pipe()
        self._res_r, res_w = os.pipe()

        def child_fds():  # the protocol's fixed fds: 3 = commands in, 4 = replies out (dup2: inheritable)
            a, b = os.dup(cmd_r), os.dup(res_w)
            os.dup2(a, 3)
            os.dup2(b, 4)

        self.proc = subprocess.Popen(
            [exe, *FLAGS, "--remote-debugging-pipe", f"--user-data-dir={self.profile}",
             f"--window-size={width},{height}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            preexec_fn=child_fds, close_fds=False)  # Python's own fds are not inheritable (PEP 446)
        os.close(cmd_r)
        os.close(res_w)
        self._buf, self._next_id, self.events, self.session = b"", 0, [], None
        try:
            page = next(t for t in self.send("Target.getTargets")["targetInfos"] if t["type"] == "page")
            self.session = self.send("Target.attachToTarget", targetId=page["targetId"], flatten=True)["sessionId"]
        except Exception:
            self.close()
            raise

    # -- protocol
    def _read_message(self, deadline):
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._res_r], [], [], left)[0]:
                raise TimeoutError("no reply from Chromium")
            chunk = os.read(self._res_r, 1 << 20)
            if not chunk:
                raise RuntimeError(f"Chromium closed the pipe (exit code {self.proc.poll()})")
            self._buf += chunk
        msg, self._buf = self._buf.split(b"\0", 1)
        return json.loads(msg)

    def send(self, method, session=None, **params):
        """Send a command and return its result; events seen meanwhile go to ``self.events``."""
        self._next_id += 1
        msg = {"id": self._next_id, "method": method, "params": params}
        browser_level = method.split(".")[0] in ("Target", "Browser")
        if session or (session is None and self.session and not browser_level):
            msg["sessionId"] = session or self.session
        os.write(self._cmd_w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + self.timeout
        while True:
            m = self._read_message(deadline)
            if m.get("id") == self._next_id:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m.get("result", {})
            self.events.append(m)

    def wait_event(self, method):
        deadline = time.monotonic() + self.timeout
        for m in self.events:
            if m.get("method") == method:
                return m
        while True:
            m = self._read_message(deadline)
            self.events.append(m)
            if m.get("method") == method:
                return m

    # -- page
    def open(self, url):
        """Navigate and wait for the load event (every non-lazy image loaded or failed)."""
        for domain in ("Page", "Runtime", "Log", "Network"):
            self.send(f"{domain}.enable")
        self.send("Page.navigate", url=url)
        self.wait_event("Page.loadEventFired")

    def evaluate(self, expression):
        r = self.send("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"evaluate: {r['exceptionDetails']}")
        return r["result"].get("value")

    def errors(self):
        """Console errors, uncaught exceptions and failed loads seen so far (as text)."""
        out = []
        for m in self.events:
            p, meth = m.get("params", {}), m.get("method")
            if meth == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                out.append("console: " + " ".join(str(a.get("value", a.get("description"))) for a in p["args"]))
            elif meth == "Runtime.exceptionThrown":
                out.append("exception: " + p["exceptionDetails"].get("text", ""))
            elif meth == "Log.entryAdded" and p["entry"]["level"] == "error":
                out.append(f"log: {p['entry'].get('text')} {p['entry'].get('url', '')}")
            elif meth == "Network.loadingFailed":
                out.append(f"network: {p.get('errorText')} ({p.get('type')})")
        return out

    def requested_urls(self):
        return [m["params"]["request"]["url"] for m in self.events if m.get("method") == "Network.requestWillBeSent"]

    def screenshot(self, path, full_page=True):
        params = {"format": "png"}
        if full_page:
            params["captureBeyondViewport"] = True
        data = self.send("Page.captureScreenshot", **params)["data"]
        with open(path, "wb") as f:
            f.write(base64.b64decode(data))

    def close(self):
        try:
            if self.proc.poll() is None:
                try:
                    self.send("Browser.close")
                except Exception:  # noqa: BLE001 - it is going away anyway
                    pass
                try:
                    self.proc.wait(5)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait(5)
        finally:
            for fd in (self._cmd_w, self._res_r):
                try:
                    os.close(fd)
                except OSError:
                    pass
            shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
