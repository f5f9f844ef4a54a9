// Decoder for the server's binary frames (layout documented in slam2d/web/frames.py).
// Header: 'SLM1', uint32 seq, uint32 n_sections, uint32 n_bytes; then per section a 16-byte header
// (char[4] tag, uint32 rows, uint32 cols, uint32 reserved) followed by rows*cols float32 values.
// The Float32Array views share the message's buffer: nothing is copied.

const MAGIC = 0x314d4c53; // 'SLM1' read as a little-endian uint32

export function decodeFrame(buf) {
  const head = new DataView(buf);
  if (buf.byteLength < 16 || head.getUint32(0, true) !== MAGIC) {
    throw new Error(`not a slam2d frame (${buf.byteLength} bytes)`);
  }
  const seq = head.getUint32(4, true);
  const n = head.getUint32(8, true);
  const total = head.getUint32(12, true);
  if (total !== buf.byteLength) throw new Error(`frame length ${buf.byteLength} != header ${total}`);
  const sections = {};
  let off = 16;
  for (let i = 0; i < n; i++) {
    const tag = String.fromCharCode(head.getUint8(off), head.getUint8(off + 1), head.getUint8(off + 2),
                                    head.getUint8(off + 3));
    const rows = head.getUint32(off + 4, true);
    const cols = head.getUint32(off + 8, true);
    off += 16;
    sections[tag] = { rows, cols, data: new Float32Array(buf, off, rows * cols) };
    off += 4 * rows * cols;
  }
  return { seq, sections };
}
