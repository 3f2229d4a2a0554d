// Replay playback: the frame grid, one step of the play clock (silences skipped) and drawing
// the frame at a time cursor. Shared by the machine page and the compare page.
import { CHUNK_S } from "./replay.js";
import { nextCovered } from "./timeline.js";

export const REPLAY_RATE_HZ = 25;
export const FRAME_S = 1 / REPLAY_RATE_HZ; // one frame step [s]
export const GAP_SKIP_S = 2; // play jumps over silences longer than this [s]
export const TRAIL_S = 20; // tip-path trail [s]

// Where play goes from `cursor` after `dtS` seconds of wall time at `speed`, in [.., to]:
// {kind: "frame" | "chunk-skipped" | "wait", cursor, gapsSkipped}. `stores`: one ReplayStore
// or several (the compare page's machines, on one clock); `coverage`: where any of them has
// data (sorted intervals). A silence longer than GAP_SKIP_S is jumped over only when every
// store is silent there: between covered intervals, inside a chunk (a frame's gapTo) or a
// whole chunk without data ("empty", "error": on to its end at once). A store whose chunk is
// still loading holds the cursor ("wait") unless another store has data at that time.
export function playStep(stores, coverage, cursor, dtS, speed, to) {
  const list = Array.isArray(stores) ? stores : [stores];
  let next = cursor + dtS * speed;
  let gaps = 0;
  const cov = nextCovered(coverage, next);
  if (coverage.length && (cov === null || cov - next > GAP_SKIP_S)) {
    next = cov === null ? to : cov;
    gaps += 1;
  }
  let resume = Infinity; // earliest time >= next where some store may have data again
  let resumeKind = "frame";
  let loading = false;
  for (const store of list) {
    const f = store.frameAt(next);
    if (f && typeof f === "object") {
      if (f.gapTo === undefined || f.gapTo - next <= GAP_SKIP_S) return { kind: "frame", cursor: Math.min(next, to), gapsSkipped: gaps };
      if (f.gapTo < resume) { resume = f.gapTo; resumeKind = "frame"; }
    } else if (f === "empty" || f === "error") {
      const end = store.from + (store.chunkIndex(next) + 1) * CHUNK_S;
      if (end < resume) { resume = end; resumeKind = "chunk-skipped"; }
    } else {
      loading = true;
    }
  }
  if (loading || resume === Infinity) return { kind: "wait", cursor, gapsSkipped: gaps };
  return { kind: resumeKind, cursor: Math.min(resume, to), gapsSkipped: gaps + (resumeKind === "frame" ? 1 : 0) };
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
