"""OPC UA beside Modbus: the live loops as an OPC UA address space, with roles (:mod:`.server`, :mod:`.users`), in
the device's process or in one of its own (:mod:`.process`)."""

from valve_emulator.device.accounts import UsersError, hash_password, load_users
from valve_emulator.opcua.process import OpcUaProcess
from valve_emulator.opcua.server import NAMESPACE, OpcUaCounters, OpcUaError, OpcUaSecurity, OpcUaServer
from valve_emulator.opcua.source import LocalSource
from valve_emulator.opcua.trust import TrustList

__all__ = ["NAMESPACE", "LocalSource", "OpcUaCounters", "OpcUaError", "OpcUaProcess", "OpcUaSecurity",
           "OpcUaServer", "TrustList", "UsersError", "hash_password", "load_users"]
