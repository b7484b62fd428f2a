"""The viewer's local web server (stdlib http.server): the static page, the mesh (packed arrays or the GLB file
itself), cameras, photos, page reports."""
from __future__ import annotations

import json
import mimetypes
import sys
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import urlparse

from trisplat.viewer.data import ViewerData

STATIC_DIR = Path(__file__).resolve().parent / "static"
MAX_REPORT_BYTES = 64 * 1024  # the page's error/ready reports are small JSON objects
HOLD_TIMEOUT_S = 300.0  # /api/hold answers after the page's first 'ready' or 'error' report, or after this
# a 1x1 transparent GIF: /api/hold's answer
PIXEL_GIF = bytes.fromhex("47494638396101000100800000000000ffffff21f90401000000002c00000000010001000002024401003b")


class ViewerServer(ThreadingHTTPServer):
    """Serves one ViewerData on 127.0.0.1. `reports` collects what the page posts to /api/report:
    {"kind": "error", "message": ...} for console errors and uncaught exceptions, {"kind": "ready", ...} once
    the mesh has been drawn."""

    daemon_threads = True

    def __init__(self, data: ViewerData, port: int = 0, host: str = "127.0.0.1", quiet: bool = True):
        self.data = data
        self.quiet = quiet
        self.reports: list[dict] = []
        self.reports_changed = threading.Condition()
        self._mesh = data.mesh_bytes()
        self._scene = json.dumps(data.scene_dict()).encode()
        self._images: dict[int, bytes] = {}
        super().__init__((host, port), _Handler)

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        return f"http://{host}:{port}/"

    def errors(self) -> list[dict]:
        return [r for r in self.reports if r.get("kind") == "error"]

    def wait_for_report(self, kind: str | tuple[str, ...], timeout_s: float) -> dict | None:
        """Block until the page posts a report of `kind` (one kind or a tuple of kinds; or timeout); returns the first
        such report or None."""
        kinds = (kind,) if isinstance(kind, str) else tuple(kind)
        with self.reports_changed:
            self.reports_changed.wait_for(lambda: any(r.get("kind") in kinds for r in self.reports), timeout_s)
        return next((r for r in self.reports if r.get("kind") in kinds), None)

    def start_background(self) -> threading.Thread:
        t = threading.Thread(target=self.serve_forever, name="trisplat-viewer", daemon=True)
        t.start()
        return t

    def image(self, index: int) -> bytes:
        if index not in self._images:
            self._images[index] = self.data.image_png(index)
        return self._images[index]


class _Handler(BaseHTTPRequestHandler):
    server: ViewerServer

    def log_message(self, format: str, *args) -> None:  # noqa: A002 - the stdlib's signature
        if not self.server.quiet:
            super().log_message(format, *args)

    def _send(self, body: bytes, content_type: str, status: HTTPStatus = HTTPStatus.OK) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def do_GET(self) -> None:  # noqa: N802 - the stdlib's name
        path = urlparse(self.path).path
        if path in ("/", "/index.html"):
            return self._static("index.html")
        if path.startswith("/static/"):
            return self._static(path[len("/static/"):])
        if path == "/api/scene.json":
            return self._send(self.server._scene, "application/json")
        if path == "/api/mesh.bin":
            return self._send(self.server._mesh, "application/octet-stream")
        if path == "/api/mesh.glb":
            if self.server.data.glb is None:
                return self._send(b"this view has no GLB", "text/plain", HTTPStatus.NOT_FOUND)
            return self._send(self.server.data.glb, "model/gltf-binary")
        if path.startswith("/api/image/") and path.endswith(".png"):
            try:
                body = self.server.image(int(path[len("/api/image/"):-4]))
            except ValueError as exc:
                return self._send(str(exc).encode(), "text/plain", HTTPStatus.NOT_FOUND)
            return self._send(body, "image/png")
        if path == "/api/hold":
            self.server.wait_for_report(("ready", "error"), HOLD_TIMEOUT_S)
            return self._send(PIXEL_GIF, "image/gif")
        if path == "/favicon.ico":
            return self._send(b"", "image/x-icon", HTTPStatus.NO_CONTENT)
        self._send(b"not found", "text/plain", HTTPStatus.NOT_FOUND)

    def do_POST(self) -> None:  # noqa: N802
        if urlparse(self.path).path != "/api/report":
            return self._send(b"not found", "text/plain", HTTPStatus.NOT_FOUND)
        n = int(self.headers.get("Content-Length", "0"))
        if n > MAX_REPORT_BYTES:
            return self._send(b"too large", "text/plain", HTTPStatus.REQUEST_ENTITY_TOO_LARGE)
        try:
            report = json.loads(self.rfile.read(n))
        except json.JSONDecodeError:
            return self._send(b"bad json", "text/plain", HTTPStatus.BAD_REQUEST)
        if not isinstance(report, dict):
            return self._send(b"bad report", "text/plain", HTTPStatus.BAD_REQUEST)
        if report.get("kind") == "error":
            print(f"viewer page error: {report.get('message')}", file=sys.stderr)
        with self.server.reports_changed:
            self.server.reports.append(report)
            self.server.reports_changed.notify_all()
        self._send(b"{}", "application/json")

    def _static(self, name: str) -> None:
        target = (STATIC_DIR / name).resolve()
        if STATIC_DIR not in target.parents or not target.is_file():
            return self._send(b"not found", "text/plain", HTTPStatus.NOT_FOUND)
        ctype = mimetypes.guess_type(target.name)[0] or "application/octet-stream"
        if target.suffix == ".js":
            ctype = "text/javascript"
        self._send(target.read_bytes(), ctype)
