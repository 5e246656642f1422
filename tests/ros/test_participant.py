"""Participant.call's resend of a query whose answer did not come (a new client's first response can be dropped by
Fast DDS before the server's writer has matched the client: CI saw a node's get_state answered into the void once).
The client is a stand-in that never answers the first request, as the dropped response looks from the caller."""

from __future__ import annotations

import time
from concurrent.futures import Future

from hood_decomp.ros.participant import Participant


class _DropsFirst:
    """A service client whose first request's answer never arrives and whose later ones are answered at once."""

    def __init__(self) -> None:
        self.sent = 0

    def service_is_ready(self) -> bool:
        return True

    def call_async(self, request: object) -> Future:
        self.sent += 1
        future: Future = Future()
        if self.sent > 1:
            future.set_result(("answer", self.sent))
        return future


def test_a_query_is_sent_again_when_its_answer_does_not_come(monkeypatch):
    """With resend_s the call answers from the second request within about resend_s; without it, it waits its whole
    budget for the first and returns None (what made bring-up report 'no answer to get_state within 120 s')."""
    with Participant("hood_decomp_test_resend") as peer:
        for resend_s, expected in ((0.3, ("answer", 2)), (None, None)):
            client = _DropsFirst()
            monkeypatch.setattr(peer.node, "create_client", lambda cls, service, c=client: c)
            monkeypatch.setattr(peer.node, "destroy_client", lambda c: None)
            start = time.monotonic()
            assert peer.call("/nobody/get_state", object, object(), 2.0, resend_s=resend_s) == expected
            elapsed = time.monotonic() - start
            assert (elapsed < 1.5) if resend_s else (elapsed >= 1.9), elapsed
