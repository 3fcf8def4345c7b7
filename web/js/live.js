// The websocket of a run's live view, reconnecting with backoff when it drops.
//
// Messages: {"type":"state","state":RunState}, {"type":"event","event":{...}},
// {"type":"lagged","missed_events":n}, {"type":"heartbeat","period_ms":P}.
//
// Compact states (`?landmarks=delta`) leave the landmarks out of `state` and carry beside it
// `landmarks: {reset, count, upsert: [[slot, id, x, y, z, xx, xy, xz, yy, yz, zz]], remove:
// [slot]}`: the landmarks that changed since the connection's previous state. The socket keeps
// the map and hands `onState` whole states either way.
//
// The server sends a heartbeat every P ms (pings too, which scripts never see): a
// connection silent for HEARTBEAT_MISSES periods is lost (a dropped network without a reset
// looks open to the browser for minutes) and is replaced.

const BACKOFF_MS = [500, 1000, 2000, 4000, 5000];
/** Heartbeat periods of silence after which the connection counts as lost (the server's). */
const HEARTBEAT_MISSES = 3;
/** The heartbeat period assumed before the server's first heartbeat [ms] (its default). */
const DEFAULT_HEARTBEAT_MS = 5000;

export class LiveSocket {
  /**
   * @param {string} url
   * @param {object} handlers `{onState, onEvent, onLagged, onStatus({state, attempt, inMs}),
   *   beforeReconnect: async () => bool}`; returning false from `beforeReconnect` stops.
   */
  constructor(url, handlers) {
    this.url = url;
    this.h = handlers;
    this.attempt = 0;
    this.stopped = false;
    this.everOpened = false;
    this.landmarks = new Map(); // slot -> landmark, for compact states
    this.bytes = 0; // characters received, for the figures of the browser test
    this.states = 0;
  }

  /** The state of a message, its landmarks restored from a compact one. */
  stateOf(msg) {
    const s = msg.state;
    const d = msg.landmarks;
    if (!d) return s;
    if (d.reset) this.landmarks.clear();
    for (const slot of d.remove || []) this.landmarks.delete(slot);
    for (const r of d.upsert || []) {
      this.landmarks.set(r[0], { slot: r[0], id: r[1], mean: [r[2], r[3], r[4]],
        cov: [r[5], r[6], r[7], r[8], r[9], r[10]] });
    }
    if (this.landmarks.size !== d.count) {
      console.error(`compact state: ${this.landmarks.size} landmarks kept, ${d.count} sent`);
    }
    s.landmarks = [...this.landmarks.values()].sort((a, b) => a.slot - b.slot);
    return s;
  }

  start() {
    this.connect();
    return this;
  }

  stop() {
    this.stopped = true;
    clearTimeout(this.timer);
    clearInterval(this.watchdog);
    if (this.ws) {
      this.ws.onclose = null;
      this.ws.onerror = null;
      this.ws.onmessage = null;
      this.ws.close();
    }
  }

  status(state, extra = {}) {
    this.state = state;
    if (this.h.onStatus) this.h.onStatus({ state, attempt: this.attempt, ...extra });
  }

  connect() {
    if (this.stopped) return;
    this.status(this.attempt ? "reconnecting" : "connecting");
    let ws;
    try {
      ws = new WebSocket(this.url);
    } catch (e) {
      this.retry();
      return;
    }
    this.ws = ws;
    this.heard = performance.now();
    this.periodMs = this.periodMs || DEFAULT_HEARTBEAT_MS;
    clearInterval(this.watchdog);
    this.watchdog = setInterval(() => this.check(ws), 250);
    ws.onopen = () => {
      this.attempt = 0;
      this.everOpened = true;
      this.heard = performance.now();
      this.status("open");
    };
    ws.onmessage = (m) => {
      this.heard = performance.now();
      this.bytes += m.data.length;
      let msg;
      try {
        msg = JSON.parse(m.data);
      } catch (_) {
        return;
      }
      if (msg.type === "state") this.states += 1;
      if (msg.type === "state" && this.h.onState) this.h.onState(this.stateOf(msg));
      else if (msg.type === "event" && this.h.onEvent) this.h.onEvent(msg.event);
      else if (msg.type === "lagged" && this.h.onLagged) this.h.onLagged(msg);
      else if (msg.type === "heartbeat" && msg.period_ms > 0) this.periodMs = msg.period_ms;
    };
    // An error is always followed by a close; reconnect from there.
    ws.onerror = () => {};
    ws.onclose = () => {
      this.ws = null;
      if (!this.stopped) this.retry();
    };
  }

  /** Drops a connection (opening or open) that has been silent too long and reconnects. */
  check(ws) {
    if (this.stopped || this.ws !== ws) return;
    if (ws.readyState !== WebSocket.OPEN && ws.readyState !== WebSocket.CONNECTING) return;
    if (performance.now() - this.heard <= HEARTBEAT_MISSES * this.periodMs) return;
    ws.onclose = null;
    ws.onerror = null;
    ws.onmessage = null;
    ws.close();
    this.ws = null;
    clearInterval(this.watchdog);
    this.retry();
  }

  async retry() {
    if (this.stopped) return;
    const wait = BACKOFF_MS[Math.min(this.attempt, BACKOFF_MS.length - 1)];
    this.attempt += 1;
    this.status("closed", { inMs: wait });
    if (this.h.beforeReconnect) {
      let go = true;
      try {
        go = await this.h.beforeReconnect();
      } catch (_) {
        go = true; // the server is unreachable: keep trying
      }
      if (!go) {
        this.stop();
        this.status("stopped");
        return;
      }
    }
    if (this.stopped) return;
    this.timer = setTimeout(() => this.connect(), wait);
  }
}
