"""A stop of ``posefuse serve``'s HTTP server while clients hold ``/events`` streams open: the
streams end at once, the server is down well before its graceful-shutdown timeout, and nothing
is cancelled mid-stream (no ``CancelledError`` traceback in the log)."""

import logging
import queue
import signal
import threading
import time

import httpx
import uvicorn
from loopback import free_port, wait_until

from posefuse.cli.serve import _server
from posefuse.service.api import create_app
from posefuse.service.settings import Settings

STREAMS = 3
GRACE_S = 5  # what serve gives open requests before it cancels them


class _QuietDaemon:
    """What /events needs of a daemon: subscriptions, and nothing ever published."""

    def __init__(self):
        self.settings = Settings()
        self.subscribed = 0
        self.unsubscribed = 0

    def subscribe(self, maxsize: int = 256) -> queue.Queue:
        self.subscribed += 1
        return queue.Queue(maxsize)

    def unsubscribe(self, q) -> None:
        self.unsubscribed += 1


def test_a_stop_with_open_event_streams_is_quick_and_quiet(caplog):
    daemon = _QuietDaemon()
    port = free_port()
    server = _server(
        uvicorn.Config(
            create_app(daemon),
            host="127.0.0.1",
            port=port,
            log_level="warning",
            timeout_graceful_shutdown=GRACE_S,
        )
    )
    serving = threading.Thread(target=server.run)
    serving.start()
    wait_until(lambda: server.started, 20)
    ended = []

    def listen():
        url = f"http://127.0.0.1:{port}/events"
        with httpx.stream("GET", url, timeout=GRACE_S * 3) as response:
            for _ in response.iter_lines():
                pass
        ended.append(True)

    clients = [threading.Thread(target=listen) for _ in range(STREAMS)]
    with caplog.at_level(logging.DEBUG):
        for c in clients:
            c.start()
        wait_until(lambda: daemon.subscribed == STREAMS, 20)
        start = time.monotonic()
        server.handle_exit(signal.SIGTERM, None)
        serving.join(GRACE_S * 3)
        took = time.monotonic() - start
        for c in clients:
            c.join(GRACE_S * 3)
    assert not serving.is_alive()
    assert took < 2.0, f"the stop took {took:.1f} s with {STREAMS} streams open"
    assert len(ended) == STREAMS and daemon.unsubscribed == STREAMS
    assert "CancelledError" not in caplog.text and "Cancel" not in caplog.text, caplog.text
    assert server.stop_signal == signal.SIGTERM
