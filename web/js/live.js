// The websocket of a run's live view, reconnecting with backoff when it drops.
//
// Messages: {"type":"state","state":RunState}, {"type":"event","event":{...}},
// {"type":"lagged","missed_events":n}.

const BACKOFF_MS = [500, 1000, 2000, 4000, 5000];

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
  }

  start() {
    this.connect();
    return this;
  }

  stop() {
    this.stopped = true;
    clearTimeout(this.timer);
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
    ws.onopen = () => {
      this.attempt = 0;
      this.everOpened = true;
      this.status("open");
    };
    ws.onmessage = (m) => {
      let msg;
      try {
        msg = JSON.parse(m.data);
      } catch (_) {
        return;
      }
      if (msg.type === "state" && this.h.onState) this.h.onState(msg.state);
      else if (msg.type === "event" && this.h.onEvent) this.h.onEvent(msg.event);
      else if (msg.type === "lagged" && this.h.onLagged) this.h.onLagged(msg);
    };
    // An error is always followed by a close; reconnect from there.
    ws.onerror = () => {};
    ws.onclose = () => {
      this.ws = null;
      if (!this.stopped) this.retry();
    };
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
