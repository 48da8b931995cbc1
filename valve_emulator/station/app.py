"""The instructor station over HTTP: aiohttp routes, the pages, server-sent events, access control.

Runs in the event loop of the Modbus device (:func:`start_station`), so an HTTP request and a Modbus request
see the same device between two ticks. The API is documented with examples in ``docs/station.md``.

Access
------
Every request has a role of the device's permission table (:mod:`valve_emulator.device.roles`, the same
roles as Modbus/TCP Security and OPC UA):

- the station token (``--web-token``: header ``Authorization: Bearer TOKEN``, or the ``station_token``
  cookie that ``/instructor?token=TOKEN`` sets, HttpOnly, SameSite=Strict) is the **instructor**;
- a user of the users file (``--web-users``, the OPC UA users file's format, :mod:`~valve_emulator.device.accounts`)
  signs in with HTTP Basic (``Authorization: Basic base64(user:password)``; a browser asks for it after a
  401) and has that user's role; a wrong name or password is 401;
- a request with neither is **anonymous**: a viewer when there is a users file (sign in to act), an operator
  (the trainee) when there is only a token, and -- on a loopback-only station with neither -- an instructor.

The instructor page ``/instructor`` and every instructor call (run, freeze, snapshots, malfunctions,
scenarios, ...) need a role that instructs; operator actions (``POST /api/loops/{unit}``) need a role that
writes the field's tag (``op``, ``sp``, ``mode``), and the write goes through ``Device.write`` under that role;
acknowledging an alarm needs a role that writes something (not a viewer). Without the right role the answer
is 401 when no credentials came, 403 when they did. :func:`start_station` refuses a station beyond loopback
without a token or a users file. The trainee's view of ``/api/state`` leaves out the instructor's
information (S, J, malfunctions, notes, score; MV unless revealed), and so does ``?view=trainee``, which the
trainee page always asks for.

Every ``POST``/``DELETE`` must carry ``Content-Type: application/json`` (a page of another site cannot send
that without a CORS preflight, which this server never grants) and a JSON object body (``{}`` when there is
nothing to say). A refused call answers ``{"error": message, "field": name}`` with a 4xx status and changes
nothing; refusals are logged at WARNING once per client (address and user) and cause (route and field) per
interval, like refused Modbus writes (:class:`~valve_emulator.device.guard.RefusalLog`).
aiohttp's own refusals -- an unknown path (404, field ``path``), a method the route does not take (405,
``method``), a body over :data:`MAX_BODY` bytes (413, ``body``) -- get the same JSON form.

Hostile clients: a body is JSON text of at most :data:`MAX_BODY` bytes that must arrive within
:data:`BODY_TIMEOUT` seconds (408 otherwise), without ``NaN``/``Infinity`` (not JSON) and nested no deeper
than Python's parser can take (400, ``body``). A connection that has not completed a request line and headers
is closed after :data:`IDLE_TIMEOUT` seconds, so slow or half-open connections do not pile up; none of them
delays the tick, which runs in the same event loop and never waits for a client.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import hmac
import json
import logging
import math
from collections.abc import Awaitable, Callable, Mapping
from importlib import resources
from typing import Any

from aiohttp import web

from valve_emulator.device.accounts import authenticate
from valve_emulator.device.guard import RefusalLog, is_loopback
from valve_emulator.device.roles import INSTRUCTOR, OPERATOR, VIEWER, Role
from valve_emulator.errors import UserError
from valve_emulator.station.core import Station, StationError

__all__ = ["make_app", "start_station", "STATION_KEY", "MAX_BODY", "BODY_TIMEOUT", "IDLE_TIMEOUT"]

_log = logging.getLogger("valve_emulator.station")
STATION_KEY = web.AppKey("station", Station)
_TOKEN = web.AppKey("token", object)
_REFUSED = web.AppKey("refused", RefusalLog)
_USERS = web.AppKey("users", object)        # name -> (Role, stored hash), or None without a users file
_ANONYMOUS = web.AppKey("anonymous", Role)  # the role of a request without credentials
_SIGNED_IN = web.AppKey("signed_in", dict)  # verified credentials -> role (PBKDF2 costs ~0.3 s per check)
_AUTH = web.RequestKey("auth", object)  # the request's checked credentials
_REALM = 'Basic realm="valve_emulator station", charset="UTF-8"'
_STREAMS = web.AppKey("streams", set)
_COOKIE = "station_token"
_STATIC = ("index.html", "instructor.html", "station.js", "station.css", "report.html")
#: Largest request body accepted (bytes): the biggest legitimate one, a scenario's YAML, is a few kB.
MAX_BODY = 1 << 20
#: Seconds a request body may take to arrive once its headers are in.
BODY_TIMEOUT = 10.0
#: Seconds a connection may stay without a complete request (aiohttp's keep-alive timeout, which also runs
#: from the moment a connection opens).
IDLE_TIMEOUT = 15.0
#: aiohttp's refusals as the API's error field
_HTTP_FIELD = {404: "path", 405: "method", 413: "body"}


def _static(name: str) -> str:
    return resources.files("valve_emulator.station").joinpath("static", name).read_text(encoding="utf-8")


def _client(request: web.Request) -> str:
    return request.remote or "?"


def _has_token(request: web.Request) -> bool:
    """Did the request bring the station token (Bearer header or cookie)?"""
    token = request.app[_TOKEN]
    if token is None:
        return False
    given = request.headers.get("Authorization", "")
    given = given[7:] if given.startswith("Bearer ") else request.cookies.get(_COOKIE, "")
    return hmac.compare_digest(given.encode(), str(token).encode())


def _basic(request: web.Request) -> tuple[str, str] | None:
    """The HTTP Basic user name and password of the request; None without them."""
    header = request.headers.get("Authorization", "")
    if not header.startswith("Basic "):
        return None
    try:
        name, colon, password = base64.b64decode(header[6:], validate=True).decode("utf-8").partition(":")
    except (ValueError, UnicodeDecodeError):
        colon = ""
    if not colon:
        raise StationError("Authorization: Basic credentials must be base64 of user:password", field="credentials",
                           status=401)
    return name, password


def _role(request: web.Request) -> Role:
    """The request's role (see the module docstring); StationError 401 for a wrong user name or password."""
    return _signed_in(request) or request.app[_ANONYMOUS]


def _signed_in(request: web.Request) -> Role | None:
    """The role the request's credentials give (the token, or a user's name and password); None without
    valid credentials of the token kind, StationError 401 for a wrong user name or password. Checked once per
    request (kept in the request)."""
    if _AUTH not in request:
        try:
            request[_AUTH] = _check_credentials(request)
        except StationError as exc:
            request[_AUTH] = exc
    found = request[_AUTH]
    if isinstance(found, StationError):
        raise found
    return found


def _check_credentials(request: web.Request) -> Role | None:
    if _has_token(request):
        return INSTRUCTOR
    users, credentials = request.app[_USERS], _basic(request)
    if users is None or credentials is None:
        return None
    signed_in = request.app[_SIGNED_IN]
    key = hashlib.sha256("\0".join(credentials).encode()).digest()
    role = signed_in.get(key)
    if role is None:
        role = authenticate(users, *credentials)
        if role is None:
            raise StationError("user name or password wrong", field="credentials", status=401)
        if len(signed_in) < 1024:
            signed_in[key] = role
    return role


def _instructor(request: web.Request) -> bool:
    return _role(request).instructs


def _need(request: web.Request, role: Role, allowed: bool, what: str) -> None:
    """Refuse (401 without credentials, 403 with) unless ``allowed``."""
    if allowed:
        return
    if _signed_in(request) is not None:
        raise StationError(f"role {role.name!r} may not {what}", field="role", status=403)
    need = "the instructor token" if request.app[_USERS] is None else "the token or a user's credentials"
    raise StationError(f"this call needs {need} (to {what})", field="token", status=401)


def _who(request: web.Request) -> str:
    """The client as the log names it: address, and the user name it signed in with."""
    header = request.headers.get("Authorization", "")
    if header.startswith("Basic "):
        try:
            name = base64.b64decode(header[6:], validate=True).decode("utf-8").partition(":")[0]
        except (ValueError, UnicodeDecodeError):
            name = "(unreadable)"
        return f"{_client(request)} (user {name[:64]!r})"
    return _client(request)


def _refuse(request: web.Request, exc: StationError) -> web.Response:
    resource = request.match_info.route.resource
    # an unknown path is logged under one key, not its own: a client making up paths must not grow the log
    cause = (request.method, resource.canonical if resource else "(no route)", exc.field)
    request.app[_REFUSED].note(_who(request), cause, "refused %s %s from %s: %s (field %s)", request.method,
                               request.path, _who(request), exc, exc.field)
    headers = {"WWW-Authenticate": _REALM} if exc.status == 401 and request.app[_USERS] is not None else None
    return web.json_response({"error": str(exc), "field": exc.field}, status=exc.status, headers=headers)


Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


def _api(*, instructor: bool = False) -> Callable[[Handler], Handler]:
    """Wrap a handler: instructor check, StationError -> JSON 4xx."""
    def wrap(handler: Handler) -> Handler:
        async def run(request: web.Request) -> web.StreamResponse:
            try:
                if instructor:
                    role = _role(request)
                    _need(request, role, role.instructs, "use the instructor's controls")
                if request.method in ("POST", "DELETE") and request.content_type != "application/json":
                    raise StationError(f"request body: Content-Type must be application/json, got "
                                       f"{request.content_type!r}", field="body", status=415)
                return await handler(request)
            except StationError as exc:
                return _refuse(request, exc)
        return run
    return wrap


@web.middleware
async def _json_errors(request: web.Request, handler: Handler) -> web.StreamResponse:
    """aiohttp's own 4xx refusals (unknown path, wrong method, body too large) as the API's JSON errors."""
    try:
        return await handler(request)
    except web.HTTPException as exc:
        if exc.status < 400 or exc.status >= 500:
            raise
        field = _HTTP_FIELD.get(exc.status, "request")
        message = {"path": f"no such page or API call: {request.method} {request.path}",
                   "method": f"{request.path} does not take {request.method}",
                   "body": f"request body: larger than {MAX_BODY} bytes"}.get(field, exc.text or exc.reason)
        return _refuse(request, StationError(message, field=field, status=exc.status))


def _not_json(constant: str) -> Any:
    raise ValueError(f"{constant} is not a JSON number")


async def _body(request: web.Request) -> dict[str, Any]:
    try:
        raw = await asyncio.wait_for(request.read(), BODY_TIMEOUT)
    except TimeoutError:
        raise StationError(f"request body: not complete after {BODY_TIMEOUT:g} s", field="body",
                           status=408) from None
    if not raw.strip():
        return {}
    try:
        body = json.loads(raw, parse_constant=_not_json)
    except (ValueError, UnicodeDecodeError) as exc:
        raise StationError(f"request body: not valid JSON ({exc})", field="body") from None
    except RecursionError:
        raise StationError("request body: JSON nested too deeply", field="body") from None
    if not isinstance(body, dict):
        raise StationError(f"request body: a JSON object is expected, got {type(body).__name__}", field="body")
    return body


def _view_instructor(request: web.Request) -> bool:
    """The instructor's view: with instructor rights, unless the query asks for ``view=trainee`` (the
    trainee page always does, so a trainee on a loopback-only station sees no more than elsewhere)."""
    return request.query.get("view") != "trainee" and _instructor(request)


def _units(request: web.Request) -> list[int] | None:
    text = request.query.get("units")
    if not text:
        return None
    try:
        return [int(u) for u in text.split(",") if u.strip()]
    except ValueError:
        raise StationError(f"query 'units' must be comma-separated unit ids, got {text!r}", field="units") from None


def _json(data: Any, status: int = 200) -> web.Response:
    return web.Response(text=json.dumps(data, allow_nan=False, default=_jsonable), status=status,
                        content_type="application/json")


def _jsonable(x: Any) -> Any:
    if hasattr(x, "item"):
        return x.item()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def _clean(x: Any) -> Any:
    """NaN and infinities (no JSON numbers) as ``null``."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    return x


def make_app(station: Station, *, token: str | None = None, users: Mapping[str, tuple[Role, str]] | None = None
             ) -> web.Application:
    """The aiohttp application of ``station`` (see the module docstring); ``users``: the users file's users
    (:func:`~valve_emulator.device.accounts.load_users`), None without one."""
    app = web.Application(client_max_size=MAX_BODY, middlewares=[_json_errors])
    app[STATION_KEY], app[_TOKEN], app[_REFUSED], app[_STREAMS] = station, token, RefusalLog(_log), set()
    app[_USERS], app[_SIGNED_IN] = users, {}
    app[_ANONYMOUS] = VIEWER if users is not None else OPERATOR if token is not None else INSTRUCTOR
    st = station
    r = app.router

    async def page(request: web.Request, name: str) -> web.Response:
        return web.Response(text=_static(name), content_type="text/html" if name.endswith(".html") else
                            "text/css" if name.endswith(".css") else "application/javascript")

    async def index(request: web.Request) -> web.Response:
        return await page(request, "index.html")

    async def instructor_page(request: web.Request) -> web.Response:
        given = request.query.get("token")
        if token is not None and given is not None and hmac.compare_digest(given.encode(), token.encode()):
            resp = web.HTTPFound("/instructor")
            resp.set_cookie(_COOKIE, token, httponly=True, samesite="Strict")
            raise resp
        try:
            _need(request, role := _role(request), role.instructs, "open the instructor page")
        except StationError as exc:
            _refuse(request, exc)
            headers = {"WWW-Authenticate": _REALM} if exc.status == 401 and users is not None else None
            return web.Response(status=exc.status, headers=headers,
                                text=f"{exc.status}: the instructor page needs the station token "
                                     f"(/instructor?token=...) or an instructor's credentials\n")
        return await page(request, "instructor.html")

    async def static(request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name not in _STATIC or name.endswith(".html"):
            raise web.HTTPNotFound()
        return await page(request, name)

    @_api()
    async def state(request: web.Request) -> web.Response:
        return _json(_clean(st.state(instructor=_view_instructor(request), units=_units(request))))

    @_api()
    async def loops(request: web.Request) -> web.Response:
        return _json({"loops": st.loop_list()})

    @_api()
    async def stream(request: web.Request) -> web.StreamResponse:
        units = _units(request)
        if units is None and st.bank.n > 50:
            units = list(st.device.units[:50])
        for u in units or ():
            st.index_of(u)
        try:
            rate = float(request.query.get("rate", "10"))
        except ValueError:
            raise StationError("query 'rate' must be a number of events per second", field="rate") from None
        if not 1 <= rate <= 50:
            raise StationError(f"query 'rate' must be 1..50 events per second, got {rate:g}", field="rate")
        instructor = _view_instructor(request)
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-cache"})
        await resp.prepare(request)
        task = asyncio.current_task()
        request.app[_STREAMS].add(task)
        try:
            while True:
                data = json.dumps(_clean(st.state(instructor=instructor, units=units)), allow_nan=False)
                await resp.write(f"data: {data}\n\n".encode())
                await asyncio.sleep(1.0 / rate)
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            request.app[_STREAMS].discard(task)
        return resp

    @_api()
    async def operate(request: web.Request) -> web.Response:
        role = _role(request)
        _need(request, role, role.writes, "operate the loops")
        return _json(st.operate(request.match_info["unit"], await _body(request), role=role))

    @_api()
    async def ack(request: web.Request) -> web.Response:
        role = _role(request)
        _need(request, role, role.writes, "acknowledge alarms")
        await _body(request)
        return _json(st.acknowledge(request.match_info["unit"]))

    @_api(instructor=True)
    async def run(request: web.Request) -> web.Response:
        await _body(request)
        await st.run()
        return _json({"running": True})

    @_api(instructor=True)
    async def freeze(request: web.Request) -> web.Response:
        await _body(request)
        await st.freeze()
        return _json({"running": False, "time": st.bank.sample_time})

    @_api(instructor=True)
    async def speed(request: web.Request) -> web.Response:
        await st.speed(await _body(request))
        return _json({"time_scale": st.device.time_scale})

    @_api(instructor=True)
    async def step(request: web.Request) -> web.Response:
        """Lockstep over HTTP, like a Modbus write of ``step``: run ``ticks`` ticks (default 1), then answer."""
        ticks = (await _body(request)).get("ticks", 1)
        if isinstance(ticks, bool) or not isinstance(ticks, int) or not 0 <= ticks <= 0xFFFF:
            raise StationError(f"field 'ticks' must be a whole number of ticks 0..65535, got {ticks!r}",
                               field="ticks")
        if not st.device.lockstep:
            raise StationError("the device is not in lockstep (serve --lockstep): it runs its own clock",
                               field="ticks", status=409)
        st.device.advance(ticks)
        return _json({"ticks": st.device.ticks, "time": st.bank.sample_time})

    @_api(instructor=True)
    async def snapshots(request: web.Request) -> web.Response:
        return _json(st.list_snapshots())

    @_api(instructor=True)
    async def save(request: web.Request) -> web.Response:
        return _json(st.save_snapshot(await _body(request)), status=201)

    @_api(instructor=True)
    async def restore(request: web.Request) -> web.Response:
        await _body(request)
        return _json(st.restore_snapshot(request.match_info["name"]))

    @_api(instructor=True)
    async def delete(request: web.Request) -> web.Response:
        st.delete_snapshot(request.match_info["name"])
        return _json({"deleted": request.match_info["name"]})

    @_api(instructor=True)
    async def malfunction(request: web.Request) -> web.Response:
        return _json(st.malfunction(await _body(request)), status=201)

    @_api(instructor=True)
    async def reveal(request: web.Request) -> web.Response:
        st.reveal(await _body(request))
        return _json({"revealed": sorted(st.revealed)})

    @_api(instructor=True)
    async def session(request: web.Request) -> web.Response:
        await _body(request)
        st.reset_session()
        return _json({"start": st.evaluation.start})

    @_api(instructor=True)
    async def scenario(request: web.Request) -> web.Response:
        from valve_emulator.station.scenario_run import load_run

        body = await _body(request)
        st.scenario = load_run(st, body)
        return _json(st.scenario.describe())

    def loaded():
        """The loaded scenario run, or a 409 naming the call that loads one."""
        if st.scenario is None:
            raise StationError("no scenario loaded (POST /api/scenario first)", field="scenario", status=409)
        return st.scenario

    @_api(instructor=True)
    async def scenario_action(request: web.Request) -> web.Response:
        await _body(request)
        run = loaded()
        action = request.match_info["action"]
        if action == "start":
            run.start(st)
        elif action == "stop":
            run.stop(st)
        else:
            raise web.HTTPNotFound()
        return _json(run.describe())

    @_api(instructor=True)
    async def hint(request: web.Request) -> web.Response:
        await _body(request)
        return _json(loaded().release_hint(st, request.match_info["id"]))

    @_api(instructor=True)
    async def report(request: web.Request) -> web.Response:
        return _json(_clean(st.report()))

    @_api(instructor=True)
    async def report_html(request: web.Request) -> web.Response:
        from valve_emulator.station.report import render_html

        return web.Response(text=render_html(st), content_type="text/html")

    @_api(instructor=True)
    async def trend(request: web.Request) -> web.Response:
        return web.Response(body=st.trend_png(request.match_info["unit"]), content_type="image/png")

    r.add_get("/", index)
    r.add_get("/instructor", instructor_page)
    r.add_get("/static/{name}", static)
    r.add_get("/api/state", state)
    r.add_get("/api/loops", loops)
    r.add_get("/api/stream", stream)
    r.add_post("/api/loops/{unit}", operate)
    r.add_post("/api/alarms/{unit}/ack", ack)
    r.add_post("/api/run", run)
    r.add_post("/api/freeze", freeze)
    r.add_post("/api/speed", speed)
    r.add_post("/api/step", step)
    r.add_get("/api/snapshots", snapshots)
    r.add_post("/api/snapshots", save)
    r.add_post("/api/snapshots/{name}/restore", restore)
    r.add_delete("/api/snapshots/{name}", delete)
    r.add_post("/api/malfunctions", malfunction)
    r.add_post("/api/reveal", reveal)
    r.add_post("/api/session", session)
    r.add_post("/api/scenario", scenario)
    r.add_post("/api/scenario/{action}", scenario_action)
    r.add_post("/api/hints/{id}/release", hint)
    r.add_get("/api/report", report)
    r.add_get("/report", report_html)
    r.add_get("/api/trend/{unit}.png", trend)

    async def stop_streams(app: web.Application) -> None:
        for task in list(app[_STREAMS]):
            task.cancel()

    app.on_shutdown.append(stop_streams)
    return app


async def start_station(station: Station, *, host: str, port: int, token: str | None = None,
                        users: Mapping[str, tuple[Role, str]] | None = None,
                        idle_timeout: float = IDLE_TIMEOUT) -> tuple[web.AppRunner, int]:
    """Serve ``station`` on ``host:port`` (0: a free port) in the running loop; returns the runner (call
    ``await runner.cleanup()`` to stop) and the bound port. Refuses a non-loopback host without a token or
    users. ``idle_timeout``: seconds a connection may stay without a complete request."""
    if token is None and users is None and not is_loopback(host):
        raise UserError(f"--web on {host} (not loopback) needs --web-token or --web-users: the instructor API "
                        f"would be open to anyone who reaches the port")
    if token is not None and len(token) < 8:
        raise UserError("--web-token must be at least 8 characters")
    runner = web.AppRunner(make_app(station, token=token, users=users), access_log=None, shutdown_timeout=1.0,
                           keepalive_timeout=idle_timeout)
    await runner.setup()
    site = web.TCPSite(runner, host, port)
    await site.start()
    bound = runner.addresses[0][1]
    return runner, int(bound)
