"""Runtime config sections load through gsfix_online.core.config like every other section."""

from __future__ import annotations

from pathlib import Path

import pytest

from gsfix_online.core.config import ConfigError, build, to_dict
from gsfix_online.runtime.config import EndpointConfig, NodeRuntimeConfig, TransportConfig


def test_transport_config_from_yaml(tmp_path: Path) -> None:
    f = tmp_path / "mapper.yaml"
    f.write_text(
        "inputs:\n"
        "  - {address: 'ipc:///tmp/gsfix/rgbd', bind: true, mode: latest}\n"
        "  - {address: 'tcp://127.0.0.1:5601', mode: reliable}\n"
        "subscriptions: ['rgbd/', 'pose/body']\n"
        "reliable_window: 32\n"
    )
    cfg = build(TransportConfig, files=[f], overrides=["linger_s=0.25"])
    assert cfg.inputs == (
        EndpointConfig("ipc:///tmp/gsfix/rgbd", True, "latest"),
        EndpointConfig("tcp://127.0.0.1:5601", False, "reliable"),
    )
    assert cfg.subscriptions == ("rgbd/", "pose/body")
    assert (cfg.reliable_window, cfg.linger_s) == (32, 0.25)
    assert build(TransportConfig, base=to_dict(cfg)) == cfg  # round trip


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        (["reliable_window=0"], "out of range"),
        (["max_message_bytes=10"], "out of range"),
        (["inputs=[{address: 'udp://x:1'}]"], "must start with ipc://"),
        (["inputs=[{address: 'tcp://hostonly'}]"], "needs host:port"),
        (["inputs=[{address: 'ipc:///a', mode: conflate}]"], "mode"),
        (["outputs=[{adress: 'ipc:///a'}]"], "unknown key"),
    ],
)
def test_bad_transport_config_is_one_line(overrides: list[str], match: str) -> None:
    with pytest.raises(ConfigError, match=match) as exc:
        build(TransportConfig, overrides=overrides)
    assert "\n" not in str(exc.value)


def test_node_runtime_config_defaults_and_ranges() -> None:
    cfg = build(NodeRuntimeConfig, overrides=["heartbeat_period_s=0.5", "on_handler_error=raise"])
    assert (cfg.heartbeat_period_s, cfg.on_handler_error, cfg.stats_period_s) == (0.5, "raise", 5.0)
    with pytest.raises(ConfigError, match="on_handler_error"):
        build(NodeRuntimeConfig, overrides=["on_handler_error=ignore"])
