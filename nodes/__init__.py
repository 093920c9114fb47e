"""Process entry points, installed as ``gsfix_online.nodes``: thin ZeroMQ event loops around the
components in ``gsfix_online.services``.

Each node parses its config section, builds one component, dispatches incoming messages on their
topic, calls the component's methods and publishes the results. Graphs name nodes by kind
through the registry in ``pyproject.toml`` (entry points of group ``gsfix_online.nodes``); the
library never imports this package.
"""
