"""The Modbus register map: every address, type and scaling of the emulated device, in one table.

Pure code (numpy and numba, no pymodbus, no I/O). Addresses are zero-based PDU addresses (mbpoll ``-0``).
Every unit id carries the same layout; only the per-loop scalings (PV range, mA table) differ.
:data:`REGISTERS` (in :mod:`~valve_emulator.device.registers.table`) is the single source of truth: every
encoder, decoder and check below is derived from its rows. :func:`registers_table` and
:func:`format_registers` render it as Markdown, CSV or JSON, and the table below is that rendering (a test
keeps them equal).

Where things are:

- :mod:`~valve_emulator.device.registers.table` -- the rows (:class:`Register`), :class:`Status`,
  :class:`Fault`, the address space (:data:`BLOCK_STRIDE`, :data:`MAX_BLOCKS`) and the read checks;
- :mod:`~valve_emulator.device.registers.words` -- data types and the word order of 32-bit values;
- :mod:`~valve_emulator.device.registers.scaling` -- :class:`Scaling`, the per-loop constants;
- :mod:`~valve_emulator.device.registers.codec` -- one register at a time in plain Python:
  :func:`encode_value`, :func:`patch`, :func:`decode_write`;
- :mod:`~valve_emulator.device.registers.kernel` -- the compiled pass that encodes every loop each tick
  (:func:`encode_image`, :func:`encode`);
- :mod:`~valve_emulator.device.registers.mapping` -- :class:`~.mapping.RegisterMap`, the map as a value:
  :data:`~.mapping.STANDARD` (this table) or a configuration's ``device.register_map`` (each tag at any
  address, type and scaling), which every Modbus adapter answers through;
- :mod:`~valve_emulator.device.registers.render` -- the documentation tables;
- :mod:`~valve_emulator.device.registers.export` -- a served map as a Kepware CSV, Ignition tag JSON or a
  Node-RED flow.

Holding registers (function codes 3, 6, 16, 22, 23)::

    | name          | table   | address | reference | type    | scale | units                    | access        |
    |---------------|---------|---------|-----------|---------|-------|--------------------------|---------------|
    | op_pct        | holding | 0       | 40001     | uint16  | 100   | % travel                 | RW            |
    | op_ma         | holding | 1       | 40002     | uint16  | 1000  | mA                       | RW            |
    | mv_pct        | holding | 2       | 40003     | uint16  | 100   | % travel                 | R             |
    | flow_pct      | holding | 3       | 40004     | uint16  | 100   | % flow                   | R             |
    | pv            | holding | 4       | 40005     | int16   | 100   | % of pv_range            | R             |
    | sp            | holding | 5       | 40006     | int16   | 100   | % of pv_range            | RW-controller |
    | mode          | holding | 6       | 40007     | uint16  | 1     | 0 manual, 1 auto         | RW-controller |
    | kc            | holding | 7       | 40008     | uint16  | 1000  | % per PV unit            | RW-controller |
    | ti            | holding | 8       | 40009     | uint16  | 10    | s (0 = no integral)      | RW-controller |
    | td            | holding | 9       | 40010     | uint16  | 10    | s                        | RW-controller |
    | S             | holding | 10      | 40011     | uint16  | 100   | % travel                 | RW-instructor |
    | J             | holding | 11      | 40012     | uint16  | 100   | % travel                 | RW-instructor |
    | status        | holding | 12      | 40013     | uint16  | 1     | bits                     | R             |
    | map_version   | holding | 13      | 40014     | uint16  | 1     |                          | R             |
    | tick          | holding | 14      | 40015     | uint32  | 1     | ticks                    | R             |
    | overruns      | holding | 16      | 40017     | uint32  | 1     | ticks                    | R             |
    | time          | holding | 18      | 40019     | float32 | 1     | s                        | R             |
    | op_f32        | holding | 20      | 40021     | float32 | 1     | % travel                 | R             |
    | mv_f32        | holding | 22      | 40023     | float32 | 1     | % travel                 | R             |
    | pv_f32        | holding | 24      | 40025     | float32 | 1     | PV units                 | R             |
    | sp_f32        | holding | 26      | 40027     | float32 | 1     | PV units                 | R             |
    | load          | holding | 28      | 40029     | int16   | 100   | % flow                   | RW-instructor |
    | noise         | holding | 29      | 40030     | uint16  | 100   | % of pv_range            | RW-instructor |
    | fault         | holding | 30      | 40031     | uint16  | 1     | bits                     | RW-instructor |
    | alarms        | holding | 31      | 40032     | uint16  | 1     | bits                     | R             |
    | comm_fault    | holding | 65280   | 465281    | uint16  | 1     | 0..5, see CommFault      | RW-instructor |
    | comm_delay_ms | holding | 65281   | 465282    | uint16  | 1     | ms added to every answer | RW-instructor |
    | step          | holding | 65296   | 465297    | uint16  | 1     | ticks to run (lockstep)  | RW            |

``comm_fault`` and ``comm_delay_ms`` belong to the unit id, not to a loop: communication faults on demand
(:class:`CommFault`, :mod:`valve_emulator.device.comm`), at fixed addresses above every loop's block.
``step`` belongs to the device's clock (every unit id answers it): in lockstep (``serve --lockstep``) writing N
runs N ticks of every loop and only then answers, so the next read sees their result; it reads 0, and
outside lockstep a write is refused (illegal data address, like OP in auto).

The rows a controller cannot write -- read-only (``R``) and instructor (``RW-instructor``) -- also appear
as input registers (function code 4) at the same addresses, so a read-only client sees injected faults
too; the input table has holes where the holding table has registers a controller writes (``op_pct`` ..
``td``), and reading a hole is an illegal address, as is reading past address 30.

Encoding (``raw = physical × scale``, rounded to the nearest integer, clipped to the type's range):

- ``op_pct``/``mv_pct``/``flow_pct``: % × 100, 0..10000. ``op_ma``: the OP as loop current through the
  loop's ``valve.ma_table`` (default linear 4–20 mA), mA × 1000. Writing either one sets OP; both read
  back consistently. The writable ``op_ma`` range is the current that maps onto 0..100 % travel
  (4000..20000 for the default table).
- ``pv``/``sp``: int16, ``10000·(x − lo)/(hi − lo)`` over the loop's ``plant.pv_range`` = (lo, hi), so
  0..10000 spans the range and values outside it stay readable down to −327.68 % / up to 327.67 %.
  ``sp`` writes must lie in 0..10000. The float32 copies carry engineering units.
- ``ti`` = 0 means no integral action (P only; the bank gets ``ti = inf``). ``kc`` must be ≥ 0.001.
- ``status`` bits: see :class:`Status`.
- ``alarms`` bits: the loop's PV alarm (:class:`AlarmBit`: 1 PV above its high limit, 2 below its low
  limit, 4 not acknowledged yet; :mod:`valve_emulator.device.alarms`).
- Instructor faults: ``load`` adds a load disturbance of ``load/100`` % flow to the plant input
  (int16, -10000..10000); ``noise`` sets the standard deviation of the PV measurement noise in % of the
  loop's ``pv_range`` × 100 (0..10000; % of span, like ``pv``, so one number means the same on every
  loop); ``fault`` bit 0 (:class:`Fault`) seizes the valve: it holds its position whatever OP does until
  the bit is cleared (other bits are refused). ``status`` bit ``SEIZED`` mirrors it.
- ``time`` (simulated s) is a float32: 0.1 s resolution holds for about six days of simulated time; for
  exact time use ``tick × dt``. ``tick`` and ``overruns`` wrap at 2³².
- 32-bit values (``uint32`` and ``float32``) use the configured word order (:class:`WordOrder`): ``ABCD``
  puts the high word at the lower address (mbpoll ``-B``), ``CDAB`` the low word first (mbpoll's default).

Access:

- ``R``: read only. ``RW``: writable; on a loop with an internal controller OP is writable only while the
  controller is in manual (it then sets the manual OP) and only within the controller's ``op_limits``.
  ``RW-controller``: writable only on loops with an internal controller, reads 0 on the others.
  ``RW-instructor``: writable only when the server allows instructor writes for the requesting client.

Errors are :class:`RegisterError` (a ``ValueError``) subclasses that name the register and carry the
refused request as attributes; the Modbus adapter alone translates them into exception codes. A rejected
multi-register write changes nothing.

Bit tables (coils: function codes 1, 5, 15; discrete inputs: function code 2)::

    | name       | table          | address | reference | type | scale | units                       | access        |
    |------------|----------------|---------|-----------|------|-------|-----------------------------|---------------|
    | auto       | coil           | 0       | 00001     | bit  | 1     | 1 auto, 0 manual            | RW-controller |
    | seized     | coil           | 1       | 00002     | bit  | 1     | 1 seizes the valve (fault)  | RW-instructor |
    | stuck      | discrete_input | 0       | 10001     | bit  | 1     | valve at rest               | R             |
    | moving     | discrete_input | 1       | 10002     | bit  | 1     | valve moving                | R             |
    | sat_low    | discrete_input | 2       | 10003     | bit  | 1     | OP clipped at 0 %           | R             |
    | sat_high   | discrete_input | 3       | 10004     | bit  | 1     | OP clipped at 100 %         | R             |
    | controller | discrete_input | 4       | 10005     | bit  | 1     | internal controller present | R             |
    | auto       | discrete_input | 5       | 10006     | bit  | 1     | controller in auto          | R             |
    | seized     | discrete_input | 6       | 10007     | bit  | 1     | valve seized (fault bit 0)  | R             |

Every bit is a view of a register (:mod:`~valve_emulator.device.registers.bits`): discrete input ``k`` is
bit ``k`` of ``status``; coil ``auto`` writes ``mode`` and coil ``seized`` writes ``fault`` with 0 or 1, so
a coil write is allowed, refused and answered exactly like the register write it stands for.
``reference`` is the one-based number an HMI tag editor shows (4xxxx holding, 3xxxx input, 0xxxx coil,
1xxxx discrete input): the table's digit followed by ``address + 1``.

Many loops per unit id (blocks)
-------------------------------
A plant-size fleet (``fleet.loops_per_unit`` > 1, see ``docs/config.md``) puts several loops behind one
unit id, each in its own *block* of :data:`BLOCK_STRIDE` = 32 registers: loop ``k`` of the unit answers
at addresses ``32k .. 32k + 31`` with exactly the map above shifted by ``32k``, so loop 3's ``pv`` is
holding register ``3·32 + 4 = 100``. A unit of ``B`` blocks spans ``0 .. 32(B−1) + 31``: at most
:data:`MAX_BLOCKS` = 2048 blocks (the 16-bit address space), so one port
serves up to 247 × 2048 loops.

- Holding reads (FC3 and the read half of FC23) may span blocks: one read of 125 registers polls about
  four loops, which is how a SCADA driver polls many loops cheaply.
- Input reads (FC4) stay inside one block (the input table has holes in every block anyway).
- Writes stay inside one block; a write that reaches the next block is an illegal address.
- Coils and discrete inputs of loop ``k`` are at ``32k + address``; a bit request stays inside one block.

With one block per unit (the default) nothing changes: the unit's map is 0..31.
"""

from valve_emulator.device.registers.codec import (
    decode_value,
    decode_write,
    encode_loop,
    encode_value,
    encode_write,
    patch,
    patches,
    status_word,
    value_decoder,
    value_encoder,
    writable_by,
    write_range,
)
from valve_emulator.device.registers.errors import (
    RegisterAccessError,
    RegisterAddressError,
    RegisterError,
    RegisterValueError,
)
from valve_emulator.device.registers.kernel import encode, encode_image, encode_words
from valve_emulator.device.registers.render import format_registers, registers_table
from valve_emulator.device.registers.scaling import Scaling
from valve_emulator.device.registers.table import *  # noqa: F403 - the table's public names, as listed in it
from valve_emulator.device.registers.table import __all__ as _table_names
from valve_emulator.device.registers.words import (
    ABCD,
    CDAB,
    DataType,
    WordOrder,
    as_word_order,
    from_words,
    split32,
    to_words,
)

__all__ = [
    *_table_names,
    "ABCD",
    "CDAB",
    "DataType",
    "RegisterAccessError",
    "RegisterAddressError",
    "RegisterError",
    "RegisterValueError",
    "Scaling",
    "WordOrder",
    "as_word_order",
    "decode_value",
    "decode_write",
    "encode",
    "encode_image",
    "encode_loop",
    "encode_value",
    "encode_write",
    "encode_words",
    "format_registers",
    "from_words",
    "patch",
    "patches",
    "registers_table",
    "split32",
    "status_word",
    "to_words",
    "value_decoder",
    "writable_by",
    "value_encoder",
    "write_range",
]
