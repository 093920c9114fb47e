"""compose_view's settings: one set of names and defaults, inherited by the repair node's and
the map server's configurations (their behaviour is tested through tests/services/test_repair.py and
tests/services/test_map_server.py)."""

from __future__ import annotations

import dataclasses

from gsfix_online.repair.compose import ComposeRules
from gsfix_online.services.map_server import ServerConfig
from gsfix_online.services.repair import Params


def test_the_repair_node_and_the_map_server_compose_by_the_same_rules():
    assert Params().rules() == ComposeRules() == ServerConfig().rules()
    # a changed setting reaches the rules from either configuration
    changed = {"far_gs_only_holes": "all", "flat_hole_std": 0.0, "distill_mask": "delivered"}
    want = dataclasses.replace(ComposeRules(), **changed)
    assert dataclasses.replace(Params(), **changed).rules() == want
    assert dataclasses.replace(ServerConfig(), **changed).rules() == want
