"""OPC UA beside Modbus: the live loops as an OPC UA address space, with roles (:mod:`.server`, :mod:`.users`)."""

from valve_emulator.device.accounts import UsersError, hash_password, load_users
from valve_emulator.opcua.server import NAMESPACE, OpcUaError, OpcUaSecurity, OpcUaServer
from valve_emulator.opcua.trust import TrustList

__all__ = ["NAMESPACE", "OpcUaError", "OpcUaSecurity", "OpcUaServer", "TrustList", "UsersError", "hash_password",
           "load_users"]
