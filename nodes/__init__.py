"""Process entry points: thin ZeroMQ event loops around the components in ``gsfix_online``.

Each node parses its config section, builds one component, dispatches incoming messages on their
topic, calls the component's pure methods and publishes the results. The runtime (transport,
wire format, launcher) and the nodes arrive with the node-runtime work; nothing here opens a
socket yet.
"""
