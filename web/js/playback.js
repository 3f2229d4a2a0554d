// Replay playback: the frame grid, one step of the play clock (silences skipped) and drawing
// the frame at a time cursor. Shared by the machine page and the compare page.
import { CHUNK_S } from "./replay.js";
import { nextCovered } from "./timeline.js";

export const REPLAY_RATE_HZ = 25;
export const FRAME_S = 1 / REPLAY_RATE_HZ; // one frame step [s]
export const GAP_SKIP_S = 2; // play jumps over silences longer than this [s]
export const TRAIL_S = 20; // tip-path trail [s]

// Where play goes from `cursor` after `dtS` seconds of wall time at `speed`, in [.., to]:
// {kind: "frame" | "chunk-skipped" | "wait", cursor, gapsSkipped}. A silence longer than
// GAP_SKIP_S (between covered intervals, or inside a chunk) is jumped over; a chunk without
// data ("empty", "error") is left for the next one at once; a chunk still loading holds the
// cursor ("wait").
export function playStep(store, coverage, cursor, dtS, speed, to) {
  let next = cursor + dtS * speed;
  let gaps = 0;
  const cov = nextCovered(coverage, next);
  if (coverage.length && (cov === null || cov - next > GAP_SKIP_S)) {
    next = cov === null ? to : cov;
    gaps += 1;
  }
  const f = store.frameAt(next);
  if (f && typeof f === "object") {
    if (f.gapTo !== undefined && f.gapTo - next > GAP_SKIP_S) { next = f.gapTo; gaps += 1; }
    return { kind: "frame", cursor: Math.min(next, to), gapsSkipped: gaps };
  }
  if (f === "empty" || f === "error") {
    const i = store.chunkIndex(next);
    return { kind: "chunk-skipped", cursor: Math.min(store.from + (i + 1) * CHUNK_S, to), gapsSkipped: gaps };
  }
  return { kind: "wait", cursor, gapsSkipped: gaps };
}

// Draws the replay frame at `t` on `crane` (3D pose, trail); returns the frame, or the chunk's
// state ("loading", "empty", "error", null) when there is none to draw.
export function drawReplay(crane, store, t) {
  const f = store.frameAt(t);
  if (!f || typeof f !== "object") return f;
  crane.apply(f);
  crane.setTrail(store.trail(t, TRAIL_S, crane.trailN));
  return f;
}
