"""The OPC UA server in either of its modes, for tests."""

#: The two ways the OPC UA server runs: in the device's process and event loop (OpcUaServer over a LocalSource),
#: and in a process of its own fed from shared memory (OpcUaProcess, what ``serve --opcua`` runs).
MODES = ("in-process", "process")


def serve_opcua(mode, device, *, loops, station=None, **settings):
    """The OPC UA server over ``device`` in ``mode`` (an async context manager; both answer ``url``, ``port``
    and ``await counters()``)."""
    from valve_emulator.opcua import OpcUaProcess, OpcUaServer
    from valve_emulator.opcua.source import LocalSource

    if mode == "process":
        return OpcUaProcess(device, loops=loops, station=station, **settings)
    return OpcUaServer(LocalSource(device, station), loops=loops, **settings)
