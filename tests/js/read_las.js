// Independent LAS/LAZ reader for tests/test_las.py, built on copc.js (npm "copc").
// Usage: node read_las.js FILE.las|FILE.laz  ->  JSON on stdout:
//   { header, vlrs, wkt, extraBytes, points: { DimensionName: [values...] } }
// Coordinates are scaled by copc.js (X * scale + offset); scan angle is in degrees.
'use strict';
const fs = require('fs');
const { Las } = require('copc');

const LAZ_BIT = 0x80; // set in the point data record format byte of a LAZ file

function cString(bytes) {
  const text = new TextDecoder('utf-8').decode(bytes);
  const end = text.indexOf('\0');
  return end < 0 ? text : text.slice(0, end);
}

// copc 0.0.8 reads an extra-bytes description from byte 60 of the 192-byte descriptor; the LAS 1.4
// R15 table puts description[32] at byte 160 (after no_data, min, max, scale, offset). Take it there.
function parseExtraBytes(vlrContent) {
  const entries = Las.ExtraBytes.parse(vlrContent);
  return entries.map((entry, k) => ({
    ...entry,
    description: cString(vlrContent.subarray(192 * k + 160, 192 * k + 192)),
  }));
}

async function main(file) {
  const buffer = fs.readFileSync(file);
  const header = Las.Header.parse(buffer);
  const vlrs = await Las.Vlr.walk(file, header);
  const wktVlr = Las.Vlr.find(vlrs, 'LASF_Projection', 2112);
  const wkt = wktVlr ? cString(await Las.Vlr.fetch(file, wktVlr)) : null;
  const ebVlr = Las.Vlr.find(vlrs, 'LASF_Spec', 4);
  const extraBytes = ebVlr ? parseExtraBytes(await Las.Vlr.fetch(file, ebVlr)) : [];
  const compressed = (buffer[104] & LAZ_BIT) !== 0;
  const start = header.pointDataOffset;
  const pointData = compressed
    ? await Las.PointData.decompressFile(buffer)
    : buffer.subarray(start, start + header.pointCount * header.pointDataRecordLength);
  const view = Las.View.create(pointData, header, extraBytes);
  const points = {};
  for (const name of Object.keys(view.dimensions)) {
    const get = view.getter(name);
    points[name] = Array.from({ length: view.pointCount }, (_, i) => get(i));
  }
  return { header, compressed, vlrs, wkt, extraBytes, points };
}

main(process.argv[2])
  .then((result) => process.stdout.write(JSON.stringify(result)))
  .catch((err) => {
    console.error(err && err.stack ? err.stack : String(err));
    process.exit(1);
  });
