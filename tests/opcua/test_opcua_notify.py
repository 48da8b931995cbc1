"""The publisher hands each value to a monitored item as asyncua's own data-change callback does, without the
throw-away objects that callback builds (docs/benchmarks.md §9.8): the same notification in the item's queue, the
same queue of one, the same change test; an item with a deadband goes through asyncua's callback."""

import pytest
from asyncua import Server, ua
from asyncua.server.monitored_item_service import MonitoredItemService

from valve_emulator.opcua.server import _GOOD, _SharedDataValue, notify


def _value(x: float) -> ua.DataValue:
    return _SharedDataValue(Value=ua.Variant(x, ua.VariantType.Double), StatusCode=_GOOD)


class _Quiet:
    def datachange_notification(self, node, val, data):
        pass


@pytest.fixture
async def items():
    """A server's variables ``ours`` and ``asyncuas``, each monitored with a queue of one by an internal
    subscription, and ``banded`` with an absolute deadband of 10 by another; (subscription, {name: (callback,
    handle)}) with the subscription's InternalSubscription."""
    server = Server()
    await server.init()
    server.set_endpoint("opc.tcp://127.0.0.1:0/notify-test/")
    async with server:
        ns = await server.register_namespace("urn:notify-test")
        objects = server.get_objects_node()
        nodes = {name: await objects.add_variable(ns, name, 0.0) for name in ("ours", "asyncuas", "banded")}
        sub = await server.create_subscription(10_000, _Quiet())   # publishes only when asked: the queue stays
        for name in ("ours", "asyncuas"):
            await sub.subscribe_data_change(nodes[name], queuesize=1)
        band = ua.DataChangeFilter(Trigger=ua.DataChangeTrigger.StatusValue,
                                   DeadbandType=ua.DeadbandType.Absolute, DeadbandValue=10.0)
        await sub._subscribe(nodes["banded"], ua.AttributeIds.Value, band, queuesize=1)
        aspace = server.iserver.aspace
        callbacks = {}
        for name, node in nodes.items():
            [(handle, callback)] = aspace._nodes[node.nodeid].attributes[ua.AttributeIds.Value] \
                .datachange_callbacks.items()
            callbacks[name] = (callback, handle)
        internal = server.iserver.subscription_service.subscriptions[sub.subscription_id]
        internal._triggered_datachanges.clear()   # the initial values
        yield internal, callbacks


def _queued(internal, callback, handle):
    service = callback.__self__
    mid = service._monitored_datachange[handle]
    return mid, internal._triggered_datachanges.get(mid, [])


async def test_a_value_is_queued_as_asyncuas_callback_queues_it_and_a_queue_of_one_keeps_the_latest(items):
    internal, callbacks = items
    (ours, our_handle), (theirs, their_handle) = callbacks["ours"], callbacks["asyncuas"]
    kept = None
    for x in (1.0, 2.0, 2.0, 3.0):   # 2.0 twice: the second is no change, not queued
        first, second = _value(x), _value(x)
        await notify(ours, our_handle, first)
        await theirs(their_handle, second)
        [(mid, mine), (their_mid, asyncuas)] = [_queued(internal, ours, our_handle),
                                                _queued(internal, theirs, their_handle)]
        assert len(mine) == len(asyncuas) == 1   # a queue of one: the latest
        if kept is None or kept[0].Value.Value != x:
            kept = (first, second)
        assert mine[0].Value is kept[0] and asyncuas[0].Value is kept[1]
        service = ours.__self__
        assert mine[0].ClientHandle == service._monitored_items[mid].client_handle
        assert asyncuas[0].ClientHandle == service._monitored_items[their_mid].client_handle
        assert service._monitored_items[mid].mvalue.get_current_datavalue() is first   # the change test's
    assert mine[0].Value.Value.Value == 3.0


async def test_an_unchanged_value_after_a_publish_is_not_queued_again(items):
    internal, callbacks = items
    ours, handle = callbacks["ours"]
    await notify(ours, handle, _value(5.0))
    internal._triggered_datachanges.clear()   # published
    await notify(ours, handle, _value(5.0))
    assert _queued(internal, ours, handle)[1] == []
    await notify(ours, handle, _SharedDataValue(Value=ua.Variant(5.0, ua.VariantType.Double),
                                                StatusCode=ua.StatusCode(ua.StatusCodes.UncertainEngineeringUnitsExceeded)))
    assert len(_queued(internal, ours, handle)[1]) == 1   # the status changed


async def test_an_item_with_a_deadband_goes_through_asyncuas_callback(items):
    internal, callbacks = items
    banded, handle = callbacks["banded"]
    await notify(banded, handle, _value(100.0))
    internal._triggered_datachanges.clear()
    await notify(banded, handle, _value(105.0))   # within the deadband of 10
    assert _queued(internal, banded, handle)[1] == []
    await notify(banded, handle, _value(120.0))
    assert [n.Value.Value.Value for n in _queued(internal, banded, handle)[1]] == [120.0]


async def test_a_callback_not_asyncuas_is_called_as_it_is():
    got = []

    async def callback(handle, dv):
        got.append((handle, dv))

    dv = _value(1.0)
    await notify(callback, 7, dv)
    assert got == [(7, dv)]



async def test_a_service_without_the_tables_notify_reads_gets_the_value_through_its_own_callback(monkeypatch):
    """Another asyncua whose service keeps its items elsewhere: ``notify`` hands the value to the service's own
    callback rather than failing on a table it cannot find."""
    handed = []

    async def callback(self, handle, dv):
        handed.append((handle, dv))

    monkeypatch.setattr(MonitoredItemService, "datachange_callback", callback)
    service = MonitoredItemService.__new__(MonitoredItemService)   # none of 2.1.0's tables
    value = _value(7.0)
    await notify(service.datachange_callback, 5, value)
    assert handed == [(5, value)]


async def test_whether_a_service_has_the_tables_notify_reads_is_decided_once_per_service(items, monkeypatch):
    """The guard looks at a service's tables at its first notification, not at every one: a server hands
    thousands of values a second to the same few services."""
    from valve_emulator.opcua import server

    internal, callbacks = items
    looked = []

    def readable(service):
        looked.append(service)
        return True

    monkeypatch.setattr(server, "_readable", readable)
    monkeypatch.setattr(server, "_READABLE", type(server._READABLE)())
    ours, handle = callbacks["ours"]
    theirs, their_handle = callbacks["asyncuas"]   # the same subscription: the same service
    for x in (1.0, 2.0, 3.0):
        await notify(ours, handle, _value(x))
        await notify(theirs, their_handle, _value(x))
    assert looked == [ours.__self__]
    assert [n.Value.Value.Value for n in _queued(internal, ours, handle)[1]] == [3.0]


async def test_a_service_whose_tables_notify_cannot_read_is_remembered_as_such(items, monkeypatch):
    """A service decided unreadable at its first notification keeps getting its values through its own callback."""
    from valve_emulator.opcua import server

    internal, callbacks = items
    ours, handle = callbacks["ours"]
    monkeypatch.setattr(server, "_READABLE", type(server._READABLE)())
    looked = []
    monkeypatch.setattr(server, "_readable", lambda service: looked.append(service) or False)
    through = []
    original = MonitoredItemService.datachange_callback

    async def counted(self, handle, dv):
        through.append(dv)
        await original(self, handle, dv)

    monkeypatch.setattr(MonitoredItemService, "datachange_callback", counted)
    bound = counted.__get__(ours.__self__)
    values = [_value(x) for x in (1.0, 2.0)]
    for value in values:
        await notify(bound, handle, value)
    assert through == values and looked == [ours.__self__]
    assert [n.Value.Value.Value for n in _queued(internal, ours, handle)[1]] == [2.0]


async def test_an_item_resolved_once_follows_a_clients_later_filter_and_mode(items):
    """The publisher resolves each item once per handle (``resolve``) and keeps it: a deadband or a monitoring mode a
    client sets afterwards (asyncua changes the item's record in place) still decides how the next values go."""
    from valve_emulator.opcua.server import _notification, resolve

    internal, callbacks = items
    ours, handle = callbacks["ours"]
    item = resolve(ours, handle)
    assert item is not None and not item.filtered()
    event = _notification(item, _value(1.0))
    assert event is not None and event.Value.Value.Value == 1.0
    mdata = ours.__self__._monitored_items[item.mid]
    mdata.filter = ua.DataChangeFilter(Trigger=ua.DataChangeTrigger.StatusValue,
                                       DeadbandType=ua.DeadbandType.Absolute, DeadbandValue=10.0)
    assert item.filtered()   # a deadband set later: through asyncua's callback
    mdata.filter = None
    assert not item.filtered()
    mdata.mode = ua.MonitoringMode.Disabled
    assert _notification(item, _value(2.0)) is None   # disabled: nothing, its values not moved on
    assert mdata.mvalue.get_current_datavalue().Value.Value == 1.0
    mdata.mode = ua.MonitoringMode.Reporting
    assert _notification(item, _value(2.0)).Value.Value.Value == 2.0
