"""OPC UA Alarms & Conditions: every loop's PV alarm as an ``AlarmConditionType`` condition.

The alarms themselves are the device's (:class:`~valve_emulator.device.alarms.PvAlarms`, the same state the
instructor station and the Modbus ``alarms`` register show). This module only turns each change into an OPC UA
event and an OPC UA acknowledgement into the device's:

- Each loop has a condition object ``PvAlarm`` under its loop object (``ns=2;s=Unit1.FIC101.PvAlarm``, linked
  by ``HasCondition``); its events come from the ``Server`` object, as Alarms & Conditions clients (UaExpert's
  Event View, a historian) subscribe to them, with ``SourceNode`` the loop and ``InputNode`` its ``pv``.
- An event is sent whenever the alarm's state changes: PV leaves its limits (``ActiveState`` true,
  ``AckedState`` false, severity 700), is acknowledged (``AckedState`` true), returns inside them (``ActiveState``
  false; ``Retain`` stays true until it is acknowledged too). Conditions that need attention are kept for
  ``ConditionRefresh`` (asyncua's own), so a client that subscribes later still sees them.
- ``Acknowledge(EventId, Comment)`` (the standard method of ``AcknowledgeableConditionType``, called on the
  condition object) acknowledges the loop's alarm on the device
  (:meth:`~valve_emulator.opcua.source.LocalSource.acknowledge_alarm`: through the station when there is one,
  the trainee's evaluation records it, ``who: opcua``). An EventId other than the condition's latest is
  ``BadEventIdUnknown``; an alarm that needs no acknowledgement is ``BadConditionBranchAlreadyAcked``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Any

from asyncua import ua
from asyncua.server.event_generator import EventGenerator

from valve_emulator.device.alarms import AlarmChange

__all__ = ["AlarmConditions", "CONDITION_NAME", "SEVERITY_ACTIVE", "SEVERITY_INACTIVE"]

_log = logging.getLogger(__name__)

#: The BrowseName of each loop's condition object and its ``ConditionName``.
CONDITION_NAME = "PvAlarm"
#: Severity (1..1000) of an event while PV is outside its limits, and once it is back.
SEVERITY_ACTIVE = 700
SEVERITY_INACTIVE = 100


class AlarmConditions:
    """The alarm conditions of an :class:`~valve_emulator.opcua.server.OpcUaServer`'s loops (see the module
    docstring): :meth:`start` once its address space is built, :meth:`stop` before it stops."""

    def __init__(self, adapter: Any) -> None:
        self.adapter = adapter
        self.source = adapter.source
        self._changes: asyncio.Queue[AlarmChange] = asyncio.Queue()
        self._generators: dict[int, EventGenerator] = {}
        self._conditions: dict[ua.NodeId, int] = {}
        self._task: asyncio.Task | None = None
        #: events sent (one per alarm change)
        self.sent = 0

    # --- nodes ----------------------------------------------------------------------------------------

    def _loop_node(self, index: int) -> ua.NodeId:
        """Loop ``index``'s object (``Unit1.FIC101``, as the adapter names it)."""
        unit, name = int(self.source.units[index]), self.adapter.loops[index].name
        return self.adapter._node_id(f"Unit{unit}.{name}")

    def condition_node(self, index: int) -> ua.NodeId:
        """The condition object of loop ``index`` (the ``ConditionId`` of its events)."""
        loop = self._loop_node(index)
        return ua.NodeId(f"{loop.Identifier}.{CONDITION_NAME}", loop.NamespaceIndex)

    async def _add_condition_objects(self) -> None:
        server = self.adapter.server
        items, refs = [], []
        for index in range(len(self.source.units)):
            node = self.condition_node(index)
            items.append(self.adapter._object_item(self._loop_node(index), node.Identifier, CONDITION_NAME))
            ref = ua.AddReferencesItem()
            ref.SourceNodeId, ref.TargetNodeId = self._loop_node(index), node
            ref.ReferenceTypeId, ref.IsForward = ua.NodeId(ua.ObjectIds.HasCondition), True
            ref.TargetNodeClass = ua.NodeClass.Object
            refs.append(ref)
            self._conditions[node] = index
        await self.adapter._add(items)
        for result in await server.iserver.isession.add_references(refs):
            result.check()

    # --- lifecycle ------------------------------------------------------------------------------------

    async def start(self) -> None:
        """Add the condition objects, link ``Acknowledge`` and ``ConditionRefresh`` (asyncua's, which it binds
        only when asked), and send an event for every alarm already raised."""
        await self._add_condition_objects()
        await self.adapter.server.iserver.setup_condition_methods()
        self.adapter.server.link_method(self.adapter.server.get_node(
            ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge)), self._acknowledge)
        self.source.alarm_listeners.append(self._changes.put_nowait)
        for change in self.source.raised_alarms():
            self._changes.put_nowait(change)
        self._task = asyncio.get_running_loop().create_task(self._send(), name="valve-emulator-opcua-alarms")

    async def stop(self) -> None:
        with contextlib.suppress(ValueError):
            self.source.alarm_listeners.remove(self._changes.put_nowait)
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    # --- events ---------------------------------------------------------------------------------------

    async def _generator(self, index: int) -> EventGenerator:
        """Loop ``index``'s event generator (its own event object: asyncua keeps the last one of a retained
        condition for ConditionRefresh), made at its first change."""
        gen = self._generators.get(index)
        if gen is None:
            gen = EventGenerator(self.adapter.server.iserver.isession)
            await gen.init(ua.NodeId(ua.ObjectIds.AlarmConditionType), emitting_node=ua.ObjectIds.Server,
                           add_generates_event=not self._generators)
            self._generators[index] = gen
        return gen

    async def _send(self) -> None:
        while True:
            change = await self._changes.get()
            try:
                await self._trigger(change)
            except Exception:   # one event that cannot be sent must not end the alarms of every loop
                _log.exception("OPC UA alarm event of loop %d not sent", change.index)

    async def _trigger(self, change: AlarmChange, comment: str = "") -> None:
        gen = await self._generator(change.index)
        ev = gen.event
        loop = self.adapter.loops[change.index]
        ev.SourceNode, ev.SourceName = self._loop_node(change.index), str(loop.name)
        ev.NodeId = self.condition_node(change.index)
        ev.InputNode = ua.NodeId(f"{ev.SourceNode.Identifier}.pv", ev.SourceNode.NamespaceIndex)
        ev.ConditionName = CONDITION_NAME
        ev.ConditionClassId = ua.NodeId(ua.ObjectIds.ProcessConditionClassType)
        ev.ConditionClassName = ua.LocalizedText("Process")
        ev.BranchId = ua.NodeId()
        ev.Retain = change.active or change.unacked
        ev.Quality = ua.StatusCode(ua.StatusCodes.Good)
        _two_state(ev, "EnabledState", True, "Enabled", "Disabled")
        _two_state(ev, "ActiveState", change.active, "Active", "Inactive")
        _two_state(ev, "AckedState", not change.unacked, "Acknowledged", "Unacknowledged")
        ev.Severity = ev.LastSeverity = SEVERITY_ACTIVE if change.active else SEVERITY_INACTIVE
        ev.Comment = ua.LocalizedText(comment)
        ev.SuppressedOrShelved = False
        await gen.trigger(message=_message(change, str(loop.name), str(getattr(loop.plant, "units", "") or "")))
        self.sent += 1

    # --- Acknowledge ----------------------------------------------------------------------------------

    async def _acknowledge(self, parent: ua.NodeId, event_id: ua.Variant, comment: ua.Variant) -> ua.StatusCode:
        index = self._conditions.get(parent)
        if index is None:
            return ua.StatusCode(ua.StatusCodes.BadNodeIdUnknown)
        gen = self._generators.get(index)
        latest = None if gen is None else gen.event.EventId
        latest = latest.Value if isinstance(latest, ua.Variant) else latest
        if latest is None or event_id.Value != latest:
            return ua.StatusCode(ua.StatusCodes.BadEventIdUnknown)
        if not await self.source.acknowledge_alarm(index):
            return ua.StatusCode(ua.StatusCodes.BadConditionBranchAlreadyAcked)
        text = comment.Value.Text if isinstance(comment.Value, ua.LocalizedText) else comment.Value
        _log.info("loop %s: PV alarm acknowledged over OPC UA (%s)", self.adapter.loops[index].name, text or "")
        return ua.StatusCode(ua.StatusCodes.Good)


def _two_state(ev: Any, name: str, value: bool, true_text: str, false_text: str) -> None:
    setattr(ev, name, ua.LocalizedText(true_text if value else false_text))
    setattr(ev, f"{name}/Id", bool(value))


def _message(change: AlarmChange, loop: str, units: str) -> str:
    """What an operator reads in an alarm list: ``FIC101: PV 53.2 m3/h above its high limit 45``."""
    u = f" {units}" if units else ""
    if change.acknowledged:
        what = "acknowledged" + ("" if change.active else "; PV back inside its limits")
    elif change.high:
        what = f"PV {change.pv:.4g}{u} above its high limit {change.hi:g}"
    elif change.low:
        what = f"PV {change.pv:.4g}{u} below its low limit {change.lo:g}"
    else:
        what = f"PV {change.pv:.4g}{u} back inside its limits {change.lo:g}..{change.hi:g}"
    return f"{loop}: {what}"
