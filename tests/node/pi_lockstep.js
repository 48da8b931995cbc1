// A PI controller in JavaScript closing the loop against `valve-emulator serve --lockstep`, on the npm Modbus
// client modbus-serial: read PV, compute, write OP, write `step` (the device runs that many ticks before it
// answers). In lockstep the run is deterministic: the same program gives the same numbers to the last digit.
//
//   node pi_lockstep.js --port 5020 [--iterations 400] [--ticks 5] [--sp 2.0] [--kc 0.5] [--ti 20]
//
// Prints one JSON line: {"iterations", "ticks", "pv": [PV read at each scan], "op": [OP written], "seconds"}.
"use strict";

const ModbusRTU = require("modbus-serial");

const PV_F32 = 24;        // holding registers of the emulator's map (valve-emulator registers)
const OP_PCT = 0;
const STEP = 65296;

function options(argv) {
  const o = { host: "127.0.0.1", port: 5020, unit: 1, iterations: 400, ticks: 5, dt: 0.1, sp: 2.0, kc: 0.5, ti: 20 };
  for (let i = 2; i < argv.length; i += 2) {
    const key = argv[i].replace(/^--/, "");
    if (!(key in o)) throw new Error(`unknown option --${key}`);
    o[key] = key === "host" ? argv[i + 1] : Number(argv[i + 1]);
  }
  return o;
}

async function readPv(client) {
  const { buffer } = await client.readHoldingRegisters(PV_F32, 2);
  return buffer.readFloatBE(0);              // float32, word order ABCD (the emulator's default)
}

async function main() {
  const o = options(process.argv);
  const client = new ModbusRTU();
  await client.connectTCP(o.host, { port: o.port });
  client.setID(o.unit);
  client.setTimeout(5000);
  const period = o.ticks * o.dt;             // controller sample time, s
  let integral = 50.0;                       // velocity-free PI: OP = Kc·e + integral of Kc·e/Ti
  const pv = [];
  const op = [];
  const start = process.hrtime.bigint();
  for (let k = 0; k < o.iterations; k++) {     // one scan: read PV, compute, write OP, write step
    const measured = await readPv(client);
    const error = o.sp - measured;
    integral = Math.min(Math.max(integral + (o.kc * period / o.ti) * error, 0), 100);
    const out = Math.min(Math.max(o.kc * error + integral, 0), 100);
    await client.writeRegister(OP_PCT, Math.round(out * 100));
    await client.writeRegister(STEP, o.ticks);
    pv.push(measured);
    op.push(out);
  }
  const seconds = Number(process.hrtime.bigint() - start) / 1e9;
  client.close(() => {});
  process.stdout.write(JSON.stringify({ iterations: o.iterations, ticks: o.ticks, pv, op, seconds }) + "\n");
}

main().catch((err) => {
  process.stderr.write(`pi_lockstep: ${err && err.stack ? err.stack : err}\n`);
  process.exit(1);
});
