// The WebSocket /ws of shared/spec/protocol.md: submit jobs, follow their messages by job id.

export class Connection {
  constructor(url, { onMessage, onStatus } = {}) {
    this.url = url;
    this.onMessage = onMessage || (() => {});
    this.onStatus = onStatus || (() => {});
    this.pending = []; // texts sent once the socket opens
    this.requests = 0;
    this.open();
  }

  open() {
    this.ws = new WebSocket(this.url);
    this.ws.onopen = () => {
      this.onStatus('connected');
      for (const text of this.pending.splice(0)) this.ws.send(text);
    };
    this.ws.onclose = () => {
      this.onStatus('disconnected');
      setTimeout(() => this.open(), 2000); // jobs keep running on the server meanwhile
    };
    this.ws.onmessage = (event) => {
      let msg;
      try {
        msg = JSON.parse(event.data);
      } catch {
        msg = { type: 'error', code: 'bad_frame', message: String(event.data).slice(0, 200) };
      }
      this.onMessage(msg);
    };
  }

  get connected() {
    return this.ws.readyState === WebSocket.OPEN;
  }

  send(message) {
    const text = JSON.stringify(message);
    if (this.connected) this.ws.send(text);
    else this.pending.push(text);
  }

  // kind: simulate | solve | heatmap; returns the request id its replies carry.
  submit(kind, sceneXml, overrides) {
    const requestId = `r${++this.requests}-${Date.now().toString(36)}`;
    const message = { type: 'submit', kind, scene_xml: sceneXml, request_id: requestId };
    if (overrides && Object.keys(overrides).length) message.overrides = overrides;
    this.send(message);
    return requestId;
  }

  cancel(jobId) {
    this.send({ type: 'cancel', job_id: jobId });
  }
}
