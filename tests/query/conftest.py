"""Fixtures of the material-query tests: a real chat-completions HTTP server on loopback,
a clean environment, and small images made on the fly."""

from __future__ import annotations

import json
import socket
import threading
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

ENV_VARS = (
    "CLFLOW_LLM_URL",
    "OPENAI_BASE_URL",
    "CLFLOW_LLM_MODEL",
    "CLFLOW_LLM_API_KEY",
    "OPENAI_API_KEY",
    "http_proxy",
    "https_proxy",
    "HTTP_PROXY",
    "HTTPS_PROXY",
    "all_proxy",
    "ALL_PROXY",
)
API_KEY = "sk-test-0123456789-SECRET"


@pytest.fixture(autouse=True)
def clean_env(monkeypatch):
    for name in ENV_VARS:
        monkeypatch.delenv(name, raising=False)


@dataclass
class Reply:
    """One scripted HTTP reply: status, JSON-able body (or raw bytes), headers, delay (s)."""

    status: int = 200
    body: object = None
    headers: dict = field(default_factory=dict)
    delay: float = 0.0


def chat(content: str | dict, finish_reason: str = "stop", **message) -> Reply:
    """A 200 chat-completions reply whose assistant message is ``content`` (dicts as JSON)."""
    text = content if isinstance(content, str) else json.dumps(content)
    return Reply(
        200,
        {
            "id": "chatcmpl-test",
            "object": "chat.completion",
            "model": "test-vision",
            "choices": [
                {
                    "index": 0,
                    "message": {"role": "assistant", "content": text, **message},
                    "finish_reason": finish_reason,
                }
            ],
        },
    )


def error(status: int, message: str, **headers) -> Reply:
    return Reply(status, {"error": {"message": message, "type": "test"}}, headers)


@dataclass
class Received:
    path: str
    headers: dict
    body: dict


class ChatServer:
    """An OpenAI-style chat-completions server on 127.0.0.1 that plays ``script``: the
    i-th request gets the i-th reply, the last reply repeats."""

    def __init__(self):
        self.script: list[Reply] = [chat("{}")]
        self.requests: list[Received] = []
        self.release = threading.Event()  # ends delayed replies at teardown
        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
        self.httpd.daemon_threads = True
        self.httpd.block_on_close = False
        self.httpd.chat = self
        self.httpd.handle_error = lambda request, address: None  # a client that timed out hung up
        self.thread = threading.Thread(target=self.httpd.serve_forever, args=(0.01,), daemon=True)
        self.thread.start()

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}/v1"

    def play(self, *replies: Reply) -> "ChatServer":
        self.script = list(replies)
        return self

    def next_reply(self) -> Reply:
        return self.script[min(len(self.requests) - 1, len(self.script) - 1)]

    def close(self):
        self.release.set()
        self.httpd.shutdown()
        self.httpd.server_close()


class _Handler(BaseHTTPRequestHandler):
    def do_POST(self):
        server: ChatServer = self.server.chat
        body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
        server.requests.append(Received(self.path, dict(self.headers), json.loads(body)))
        reply = server.next_reply()
        if reply.delay:
            server.release.wait(reply.delay)
        payload = reply.body if isinstance(reply.body, bytes) else json.dumps(reply.body).encode()
        self.send_response(reply.status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(payload)))
        for k, v in reply.headers.items():
            self.send_header(k.replace("_", "-"), str(v))
        self.end_headers()
        self.wfile.write(payload)

    def log_message(self, *args):
        pass


@pytest.fixture
def server():
    s = ChatServer()
    yield s
    s.close()


@pytest.fixture
def refused_url():
    """A loopback URL whose port is bound but not listening: connections are refused."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    yield f"http://127.0.0.1:{sock.getsockname()[1]}/v1"
    sock.close()


@pytest.fixture
def photo(tmp_path):
    """(path, pixels) of a 64x48 image with a distinct value at every pixel."""
    import cv2

    y, x = np.mgrid[0:48, 0:64]
    pixels = np.stack([x * 4, y * 5, (x + y) % 256], axis=-1).astype(np.uint8)
    path = tmp_path / "rubber_duck.png"
    assert cv2.imwrite(str(path), pixels)
    return path, pixels
