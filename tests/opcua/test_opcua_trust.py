"""OPC UA security beside the roles: the trust list of client certificates (PKI/trusted, PKI/rejected),
``--opcua-trust-all`` on loopback only, and users of every role of the permission table writing what their role
allows. Client: asyncua in process."""

import logging
import shutil
import subprocess

import pytest
from asyncua import Client, ua
from required import tool

from valve_emulator.cli import main
from valve_emulator.config import server_from_mapping
from valve_emulator.device.accounts import hash_password, load_users
from valve_emulator.device.certs import opcua_certificate
from valve_emulator.device.roles import RoleTable
from valve_emulator.device.server import EmulatorServer
from valve_emulator.opcua import NAMESPACE, OpcUaError, OpcUaSecurity, UsersError
from valve_emulator.opcua.server import APPLICATION_URI

from .conftest import DEVICE
from .modes import serve_opcua

CLIENT_URI = "urn:valve-emulator:trust-test-client"
PASSWORDS = {"vera": ("viewer", "look"), "otto": ("operator", "run"), "ines": ("instructor", "teach"),
             "tina": ("tuner", "tune")}


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The server's and a client's application certificates, and a users file with one user per role."""
    d = tmp_path_factory.mktemp("opcua-trust")
    opcua_certificate(d, application_uri=APPLICATION_URI)
    opcua_certificate(d, application_uri=CLIENT_URI, name="client")
    lines = [f"  {name}: {{role: {role}, password: '{hash_password(pw, iterations=1000)}'}}"
             for name, (role, pw) in PASSWORDS.items()]
    (d / "users.yaml").write_text("users:\n" + "\n".join(lines) + "\n")
    return d


@pytest.fixture
def roles_config():
    return server_from_mapping({**DEVICE, "device": {"tick": 0.1, "roles": {"tuner": ["kc", "ti", "td"]}}})


def _security(files, pki, **kw):
    return OpcUaSecurity(policies=("Basic256Sha256",), certificate=files / "server.der",
                         private_key=files / "server-key.pem", pki=pki, **kw)


async def _secure_client(url, files):
    client = Client(url)
    await client.set_security_string(f"Basic256Sha256,SignAndEncrypt,{files / 'client.der'},"
                                     f"{files / 'client-key.pem'},{files / 'server.der'}")
    client.application_uri = CLIENT_URI
    return client


async def test_an_unknown_client_certificate_is_rejected_and_trusted_once_moved(opcua_mode, config, files, tmp_path,
                                                                                caplog):
    caplog.set_level(logging.WARNING, logger="valve_emulator.opcua.trust")
    pki = tmp_path / "pki"
    async with EmulatorServer(config, port=0, time_scale=0) as srv, \
            serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0, security=_security(files, pki)) as opc:
        with pytest.raises(ua.UaStatusCodeError) as err:
            async with await _secure_client(opc.url, files):
                pass
        assert type(err.value).__name__ == "BadCertificateUntrusted"
        [rejected] = (pki / "rejected" / "certs").iterdir()
        assert rejected.name.startswith("valve_emulator OPC UA client [") and rejected.suffix == ".der"
        assert rejected.read_bytes() == (files / "client.der").read_bytes()
        [line] = [r.getMessage() for r in caplog.records if r.name == "valve_emulator.opcua.trust"]
        assert CLIENT_URI in line and "CN=valve_emulator OPC UA client" in line and str(rejected) in line
        # the administrator trusts it: moved from rejected to trusted, no restart
        shutil.move(rejected, pki / "trusted" / "certs" / rejected.name)
        async with await _secure_client(opc.url, files) as client:
            ns = await client.get_namespace_index(NAMESPACE)
            assert ns > 0
        counters = await opc.counters()
        assert (counters.trust_accepted, counters.trust_refused) == (1, 1)


async def test_a_client_whose_uri_is_not_its_certificates_is_refused_before_the_trust_list(opcua_mode, config, files,
                                                                                           tmp_path, caplog):
    caplog.set_level(logging.WARNING, logger="valve_emulator.opcua.trust")
    pki = tmp_path / "pki"
    async with EmulatorServer(config, port=0, time_scale=0) as srv, \
            serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0, security=_security(files, pki)) as opc:
        client = await _secure_client(opc.url, files)
        client.application_uri = "urn:someone:else"
        with pytest.raises(ua.UaStatusCodeError) as err:
            async with client:
                pass
        assert type(err.value).__name__ == "BadCertificateUriInvalid"
    assert not any((pki / "rejected" / "certs").iterdir())
    [line] = [r.getMessage() for r in caplog.records if r.name == "valve_emulator.opcua.trust"]
    assert "urn:someone:else" in line and "BadCertificateUriInvalid" in line


async def test_a_certificate_signed_by_a_trusted_ca_is_accepted(config, tmp_path):
    """A CA certificate in trusted/certs admits the client certificates it signed (the Modbus test CA here)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    from valve_emulator.device.certs import modbus_certificate
    from valve_emulator.opcua.trust import TrustList

    modbus_certificate(tmp_path, "client", role="operator")
    trust = TrustList(tmp_path / "pki")
    trust.create()
    client = x509.load_pem_x509_certificate((tmp_path / "client.pem").read_bytes())
    assert not trust.is_trusted(client)
    ca = x509.load_pem_x509_certificate((tmp_path / "ca.pem").read_bytes())
    (trust.trusted / "ca.der").write_bytes(ca.public_bytes(serialization.Encoding.DER))
    assert trust.is_trusted(client)


async def test_trust_all_accepts_any_client_and_writes_nothing(opcua_mode, config, files, tmp_path):
    security = _security(files, None, trust_all=True)
    async with EmulatorServer(config, port=0, time_scale=0) as srv, \
            serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0, security=security) as opc:
        client = await _secure_client(opc.url, files)
        async with client:
            assert await client.get_namespace_index(NAMESPACE) > 0
        assert (await opc.counters()).trust_accepted == 1
    assert list(tmp_path.iterdir()) == []


def test_trust_all_is_refused_beyond_loopback_and_a_secure_policy_needs_a_trust_list(files, tmp_path):
    users = load_users(files / "users.yaml", RoleTable.of([("tuner", ("kc",))]))
    with pytest.raises(OpcUaError, match="--opcua-trust-all: refusing .* '0.0.0.0'"):
        _security(files, None, trust_all=True, users=users).check("0.0.0.0")
    with pytest.raises(OpcUaError, match="needs a trust list"):
        _security(files, None, users=users).check("127.0.0.1")
    _security(files, None, trust_all=True).check("127.0.0.1")
    _security(files, tmp_path / "pki", users=users).check("0.0.0.0")


def test_serve_refuses_trust_all_beyond_loopback_naming_the_flag(files, tmp_path, capsys):
    users = tmp_path / "users.yaml"
    users.write_text(f"users:\n  otto: {{role: operator, password: '{hash_password('run', iterations=1000)}'}}\n")
    code = main(["serve", "--host", "0.0.0.0", "--port", "0", "--opcua", "0", "--opcua-policy", "Basic256Sha256",
                 "--opcua-cert", str(files / "server.der"), "--opcua-key", str(files / "server-key.pem"),
                 "--opcua-users", str(users), "--opcua-trust-all"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "--opcua-trust-all" in err and "0.0.0.0" in err and "Traceback" not in err


def test_a_users_file_with_a_role_outside_the_table_is_refused_naming_the_key(files, tmp_path):
    with pytest.raises(UsersError, match=r"users\.tina\.role: must be a role of the permission table"):
        load_users(files / "users.yaml")                      # no device.roles: no "tuner"
    users = load_users(files / "users.yaml", RoleTable.of([("tuner", ("kc", "ti", "td"))]))
    assert {name: role.name for name, (role, _) in users.items()} == {n: r for n, (r, _) in PASSWORDS.items()}


#: variable of FIC101 -> value written; which roles may write it
WRITES = {"sp": (20.0, {"operator", "instructor"}), "kc": (0.5, {"instructor", "tuner"}),
          "S": (1.5, {"instructor"}), "mode": (0, {"operator", "instructor"})}


@pytest.mark.parametrize("user", list(PASSWORDS))
async def test_each_user_writes_what_the_role_allows_and_nothing_else(opcua_mode, roles_config, files, user):
    role, password = PASSWORDS[user]
    users = load_users(files / "users.yaml", RoleTable.from_config(roles_config))
    async with EmulatorServer(roles_config, port=0, time_scale=0) as srv, \
            serve_opcua(opcua_mode, srv.device, loops=roles_config.loops, port=0,
                        security=OpcUaSecurity(users=users)) as opc:
        client = Client(opc.url)
        client.set_user(user)
        client.set_password(password)
        async with client:
            ns = await client.get_namespace_index(NAMESPACE)
            loop = await client.nodes.objects.get_child([f"{ns}:ValveEmulator", f"{ns}:Unit1", f"{ns}:FIC101"])
            assert await (await loop.get_child(f"{ns}:pv")).read_value() is not None   # everyone reads
            for var, (value, allowed) in WRITES.items():
                node = await loop.get_child(f"{ns}:{var}")
                variant = ua.VariantType.Double if var != "mode" else ua.VariantType.UInt16
                if role in allowed:
                    await node.write_value(ua.DataValue(ua.Variant(value, variant)))
                else:
                    with pytest.raises(ua.UaStatusCodeError) as err:
                        await node.write_value(ua.DataValue(ua.Variant(value, variant)))
                    assert type(err.value).__name__ == "BadUserAccessDenied", (user, var)
        srv.device.advance(1)
        bank = srv.device.bank
        assert (float(bank._sp[0]) == pytest.approx(20.0)) == ("sp" in _written(role))
        assert (float(bank.kc[0]) == pytest.approx(0.5)) == ("kc" in _written(role))
        assert (float(bank.S[0]) == pytest.approx(1.5)) == ("S" in _written(role))
        assert (await opc.counters()).refused == len(WRITES) - len(_written(role))


def _written(role):
    return {var for var, (_, allowed) in WRITES.items() if role in allowed}


def _openssl_client_certificate(d, uri):
    """A client certificate made with openssl as docs/opcua.md shows (DER for the trust list)."""
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "365",
                    "-keyout", str(d / "client-key.pem"), "-out", str(d / "client.pem"),
                    "-subj", "/CN=my-client/O=plant",
                    "-addext", f"subjectAltName=URI:{uri},DNS:localhost",
                    "-addext", "keyUsage=critical,digitalSignature,nonRepudiation,keyEncipherment,dataEncipherment",
                    "-addext", "extendedKeyUsage=clientAuth"], check=True, capture_output=True)
    subprocess.run(["openssl", "x509", "-in", str(d / "client.pem"), "-outform", "der", "-out", str(d / "client.der")],
                   check=True, capture_output=True)


async def test_a_client_certificate_made_with_openssl_and_trusted_ahead_gets_a_session(opcua_mode, config, files,
                                                                                        tmp_path):
    tool("openssl", "apt-get install openssl")
    uri = "urn:example:my-client"
    _openssl_client_certificate(tmp_path, uri)
    pki = tmp_path / "pki"
    (pki / "trusted" / "certs").mkdir(parents=True)
    shutil.copy(tmp_path / "client.der", pki / "trusted" / "certs")
    async with EmulatorServer(config, port=0, time_scale=0) as srv, \
            serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0, security=_security(files, pki)) as opc:
        client = Client(opc.url)
        await client.set_security_string(f"Basic256Sha256,SignAndEncrypt,{tmp_path / 'client.der'},"
                                         f"{tmp_path / 'client-key.pem'},{files / 'server.der'}")
        client.application_uri = uri
        async with client:
            assert await client.get_namespace_index(NAMESPACE) > 0
        assert (await opc.counters()).trust_accepted == 1
    assert not any((pki / "rejected" / "certs").iterdir())
