"""The OPC UA process's entry point: ``python -m valve_emulator.opcua FD``, started by
:class:`~valve_emulator.opcua.process.OpcUaProcess` with its end of a socket pair (FD); not a command for users."""

import sys

from valve_emulator.opcua.remote import child_main

if __name__ == "__main__":
    child_main(int(sys.argv[1]))
