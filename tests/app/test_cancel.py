"""The app's cancel scope: a relight stops when its client has gone, and only then."""

from __future__ import annotations

import copy

import pytest
import torch

from difareli.app.cache import Cancelled, CancelScope, attach


def test_a_deep_copied_network_reads_the_one_cancel_scope():
    # The runtime's bf16 inference copy deep-copies the hooked network while a request holds the lock: the copy
    # must read the scope's current check, not the one of the request that made it (whose socket is closed later).
    net, scope = torch.nn.Linear(2, 2), CancelScope()
    attach(net, scope)
    scope.check = lambda: True  # the request during which the copy is made; its client goes afterwards
    twin = copy.deepcopy(net)
    scope.check = lambda: False  # the next request: its client is there
    twin(torch.zeros(1, 2))
    scope.check = lambda: True
    with pytest.raises(Cancelled):
        twin(torch.zeros(1, 2))
    assert scope.cancelled == 1
    scope.check = None  # between requests nothing is checked
    net(torch.zeros(1, 2))
