#!/usr/bin/env python3
"""A Foxglove viewer that subscribes to every channel of a live view and then never reads: the worst
client a `pntr-server --foxglove` can have (a laptop on a dropping Wi-Fi, a tab in the background).
For measuring what such viewers cost the robots (BENCHMARKS.md, "Slow Foxglove viewers").

Usage: stalled_viewer.py ws://HOST:PORT [--viewers N] [--seconds S] [--protocol NAME]

Opens N connections (default 2) with the Sec-WebSocket-Protocol NAME (default foxglove.sdk.v1),
reads each one's advertisements, subscribes to all channels, then holds the sockets open without
reading for S seconds (default: until killed). Standard library only.
"""
import argparse, base64, json, os, socket, struct, sys, time


def frame(payload: bytes) -> bytes:
    """One masked client text frame (RFC 6455, 5.2)."""
    mask = os.urandom(4)
    n = len(payload)
    head = b'\x81' + (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack('>H', n))
    return head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


def read_frame(s: socket.socket, buf: bytearray):
    """(opcode, payload) of the next server frame, reading more from `s` as needed."""
    def need(k):
        while len(buf) < k:
            chunk = s.recv(65536)
            if not chunk:
                raise ConnectionError('closed')
            buf.extend(chunk)
    need(2)
    op, n = buf[0] & 0x0F, buf[1] & 0x7F
    at = 2
    if n == 126:
        need(4); n = struct.unpack('>H', bytes(buf[2:4]))[0]; at = 4
    elif n == 127:
        need(10); n = struct.unpack('>Q', bytes(buf[2:10]))[0]; at = 10
    need(at + n)
    payload = bytes(buf[at:at + n])
    del buf[:at + n]
    return op, payload


def stalled(url: str, protocol: str) -> socket.socket:
    host, port = url.removeprefix('ws://').rstrip('/').rsplit(':', 1)
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 64 * 1024)  # a small window: stalls sooner
    s.settimeout(10)
    s.connect((host, int(port)))
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall((f'GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n'
               f'Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {protocol}\r\n\r\n').encode())
    buf = bytearray()
    while b'\r\n\r\n' not in buf:
        buf.extend(s.recv(4096))
    head, _, rest = bytes(buf).partition(b'\r\n\r\n')
    if not head.startswith(b'HTTP/1.1 101'):
        sys.exit(f'{url}: {head.decode(errors="replace")}')
    buf = bytearray(rest)
    channels, deadline = [], time.time() + 10
    while len(channels) < 7 and time.time() < deadline:
        op, payload = read_frame(s, buf)
        if op == 1:
            m = json.loads(payload)
            if m.get('op') == 'advertise':
                channels += [c['id'] for c in m['channels']]
    subs = [{'id': i, 'channelId': c} for i, c in enumerate(channels)]
    s.sendall(frame(json.dumps({'op': 'subscribe', 'subscriptions': subs}).encode()))
    return s


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('url')
    ap.add_argument('--viewers', type=int, default=2)
    ap.add_argument('--seconds', type=float, default=None)
    ap.add_argument('--protocol', default='foxglove.sdk.v1')
    a = ap.parse_args()
    sockets = [stalled(a.url, a.protocol) for _ in range(a.viewers)]
    print(f'{len(sockets)} viewers subscribed to everything, reading nothing', flush=True)
    time.sleep(a.seconds if a.seconds is not None else 1e9)


if __name__ == '__main__':
    main()
