// The WebSocket /ws of shared/spec/protocol.md: submit jobs, follow their messages by job id.
//
// A server that needs a token (protocol.md, "Access") is opened as http://HOST:PORT/?token=TOKEN:
// the page reads the token from its own URL and sends it with every request it makes, as a Bearer
// header on REST (serverFetch) and as ?token= on the WebSocket URL (which cannot carry headers).

export const token = new URLSearchParams(window.location.search).get('token');

const CLOSE_UNAUTHORIZED = 4401;

// fetch() for the server's own routes, with the page's token.
export function serverFetch(url, init = {}) {
  if (!token || new URL(url, window.location.href).origin !== window.location.origin) return fetch(url, init);
  const headers = new Headers(init.headers || {});
  headers.set('Authorization', `Bearer ${token}`);
  return fetch(url, { ...init, headers });
}

// The WebSocket URL ws(s)://HOST:PORT/ws of this page, with its token.
export function socketUrl(path = 'ws') {
  const url = new URL(path, window.location.href);
  url.protocol = url.protocol === 'https:' ? 'wss:' : 'ws:';
  url.search = '';
  if (token) url.searchParams.set('token', token);
  return url.href;
}

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
    this.ws.onclose = (event) => {
      if (event.code === CLOSE_UNAUTHORIZED) { // trying again cannot help
        this.onStatus('unauthorized');
        this.onMessage({
          type: 'error', code: 'unauthorized',
          message: `the server needs a token: open this page as ${window.location.origin}/?token=TOKEN`,
        });
        return;
      }
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

  // kind: simulate | solve | heatmap | train; returns the request id its replies carry.
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
