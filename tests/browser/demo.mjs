// Starts the real `bgkmap demo` on free loopback ports in a temporary data directory and
// stops it (SIGINT, as Ctrl-C) when done.

import { spawn } from 'node:child_process';
import { mkdtempSync, rmSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join } from 'node:path';
import { createInterface } from 'node:readline';

export function bgkmapBinary() {
  if (process.env.BGKMAP_BIN) return process.env.BGKMAP_BIN;
  const target = process.env.CARGO_TARGET_DIR || new URL('../../target', import.meta.url).pathname;
  return join(target, 'debug', 'bgkmap');
}

// Resolves once the demo has streamed its scans and serves: { http, grpc, stop() }.
export function startDemo(extraArgs = [], timeoutMs = 180_000) {
  const dir = mkdtempSync(join(tmpdir(), 'bgkmap-viewer-'));
  const args = ['demo', '--dir', dir, '--grpc-listen', '127.0.0.1:0', '--http-listen', '127.0.0.1:0', ...extraArgs];
  const child = spawn(bgkmapBinary(), args, { stdio: ['ignore', 'pipe', 'pipe'] });
  let stderr = '';
  child.stderr.on('data', (d) => (stderr += d));
  const stop = async () => {
    if (child.exitCode === null) {
      const exited = new Promise((r) => child.once('exit', r));
      child.kill('SIGINT');
      await exited;
    }
    rmSync(dir, { recursive: true, force: true });
  };
  return new Promise((resolve, reject) => {
    const timer = setTimeout(() => {
      child.kill('SIGKILL');
      reject(new Error(`bgkmap demo did not start in time; stderr:\n${stderr}`));
    }, timeoutMs);
    let addrs = null;
    createInterface({ input: child.stdout }).on('line', (line) => {
      const m = line.match(/server on grpc (\S+), http (\S+),/);
      if (m) addrs = { grpc: m[1], http: m[2] };
      if (line.startsWith('Serving until Ctrl-C') && addrs) {
        clearTimeout(timer);
        resolve({ ...addrs, dir, stop });
      }
    });
    child.once('exit', (code) => {
      clearTimeout(timer);
      reject(new Error(`bgkmap demo exited (${code}) before serving; stderr:\n${stderr}`));
    });
  });
}
