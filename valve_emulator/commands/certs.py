"""``valve-emulator certs``: certificates and password hashes for the secure interfaces.

- ``--opcua DIR [--host H ...]``: a self-signed OPC UA application certificate (``DIR/server.der``) and key
  (``DIR/server-key.pem``) whose ApplicationUri is the server's, for ``serve --opcua-cert/--opcua-key``;
- ``--modbus DIR [--modbus-role ROLE ...] [--host H ...] [--config CONFIG]``: a test CA (``ca.pem``, kept if
  present), the server's certificate (``server.pem``) and one client certificate per role
  (``client-ROLE.pem``) carrying the Modbus/TCP Security role extension, for
  ``serve --tls-port/--tls-cert/--tls-key/--tls-ca``. A role must be in the permission table: ``viewer``,
  ``operator``, ``instructor``, or a custom role of ``device.roles`` in ``--config CONFIG`` (a certificate
  with any other role would get no session, so none is made);
- ``--hash-password``: read a password on standard input, print the hash a users file stores.
"""

from __future__ import annotations

import argparse
import getpass
import sys
from pathlib import Path

from valve_emulator.commands._files import user_files
from valve_emulator.errors import UserError

NAME = "certs"
HELP = "make OPC UA and Modbus/TLS certificates (with role extensions) and password hashes for a users file"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--opcua", type=Path, metavar="DIR", help="write an OPC UA application certificate and key here")
    p.add_argument("--modbus", type=Path, metavar="DIR",
                   help="write a test CA, a server certificate and client certificates for Modbus/TLS here")
    p.add_argument("--modbus-role", action="append", metavar="ROLE", default=None,
                   help="a client certificate with this role (viewer, operator, instructor, or a custom role of "
                        "--config; repeatable; default operator and instructor)")
    p.add_argument("--config", type=Path, metavar="CONFIG",
                   help="the server config whose device.roles defines the custom roles --modbus-role may name")
    p.add_argument("--host", action="append", metavar="HOST", default=None,
                   help="a name or address the server is reached at (repeatable; default localhost, 127.0.0.1)")
    p.add_argument("--hash-password", action="store_true",
                   help="read a password on standard input and print its hash for a users file")


def run(args: argparse.Namespace) -> int:
    with user_files({"--opcua": args.opcua, "--modbus": args.modbus, "--config": args.config}):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    if not (args.opcua or args.modbus or args.hash_password):
        raise UserError("certs: give --opcua DIR, --modbus DIR or --hash-password")
    if (args.modbus_role or args.config) and not args.modbus:
        raise UserError("--modbus-role and --config need --modbus DIR")
    hosts = tuple(args.host or ("localhost", "127.0.0.1"))
    if args.hash_password:
        from valve_emulator.device.accounts import hash_password

        password = getpass.getpass("password: ") if sys.stdin.isatty() else sys.stdin.readline().rstrip("\n")
        if not password:
            raise UserError("--hash-password: an empty password")
        print(hash_password(password))
    if args.opcua:
        from valve_emulator.device.certs import opcua_certificate
        from valve_emulator.opcua.server import APPLICATION_URI

        cert, key = opcua_certificate(args.opcua, application_uri=APPLICATION_URI, hosts=hosts)
        print(f"OPC UA application certificate {cert} (ApplicationUri {APPLICATION_URI}), key {key}")
    if args.modbus:
        from valve_emulator.device.certs import modbus_ca, modbus_certificate

        roles = _modbus_roles(args.modbus_role or ("operator", "instructor"), args.config)
        ca, _ = modbus_ca(args.modbus)
        server, _ = modbus_certificate(args.modbus, "server", server=True, hosts=hosts)
        print(f"Modbus/TLS: CA {ca}, server certificate {server}")
        for role in roles:
            cert, _ = modbus_certificate(args.modbus, f"client-{role}", role=role)
            print(f"Modbus/TLS: client certificate {cert} with role {role!r}")
    return 0


def _modbus_roles(roles: list[str] | tuple[str, ...], config: Path | None) -> list[str]:
    """``roles``, each checked against the permission table (the built-in roles, and ``device.roles`` of
    ``config``) before any file is written; ``UserError`` naming ``--modbus-role`` for one that is not in it."""
    from valve_emulator.device.roles import DEFAULT_ROLES, RoleTable

    table = DEFAULT_ROLES
    if config is not None:
        from valve_emulator.config import load_server

        table = RoleTable.from_config(load_server(config))
    for role in roles:
        if role not in table:
            hint = "" if config is not None else "; a custom role needs --config CONFIG with device.roles"
            raise UserError(f"--modbus-role {role!r}: not a role of the permission table ({table.describe()})"
                            f"{hint}: a certificate with it would get no session")
    return list(roles)
