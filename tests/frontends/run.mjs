// Reads one JSON document on stdin and writes one JSON line per status cycle on stdout:
//     {"cycles": [{"eventtime": s, "status": {object: {field: value}}, "wallclock"?: s}, ...],
//      "metadata": {...server.files.metadata...} | null,
//      "database": {"mainsail": {...namespace value...}, "fluidd": {...}},
//      "history": [...server.history.list jobs...]}
// Each line: {"eventtime", "now_ms", "mainsail": {getter: value}, "fluidd": {getter: value}}.
// Date.now() is the cycle's wall clock (`wallclock`, else `eventtime`) while the getters run,
// so an ETA (Date.now() + time left) can be read back as a time left.
import path from 'node:path'
import { pathToFileURL } from 'node:url'

const outDir = process.argv[2]
const mainsail = await import(pathToFileURL(path.join(outDir, 'mainsail.cjs')).href)
const fluidd = await import(pathToFileURL(path.join(outDir, 'fluidd.cjs')).href)

let text = ''
for await (const chunk of process.stdin) text += chunk
const input = JSON.parse(text)
const database = input.database ?? {}
const realNow = Date.now
let nowMs = realNow()
Date.now = () => nowMs

const stores = [
  ['mainsail', mainsail, mainsail.createStore(database.mainsail ?? {}, input.metadata)],
  ['fluidd', fluidd, fluidd.createStore(database.fluidd ?? {}, input.metadata, input.history)]
]
const lines = []
for (const cycle of input.cycles) {
  nowMs = (cycle.wallclock ?? cycle.eventtime) * 1000
  const line = { eventtime: cycle.eventtime, now_ms: nowMs }
  for (const [name, front, store] of stores) {
    front.feed(store, cycle.status)
    line[name] = front.read(store)
  }
  lines.push(JSON.stringify(line))
}
process.stdout.write(lines.join('\n') + (lines.length ? '\n' : ''))
