// Independent COPC reader for tests/test_copc.py, built on copc.js (npm "copc").
// Usage: node read_copc.js FILE.copc.laz  ->  JSON on stdout:
//   { header, info, wkt, extraBytes, nodes: { "d-x-y-z": pointCount }, points: { Dimension: [...] } }
// Reads as a viewer does: Copc.create (header, VLRs, COPC info), Copc.loadHierarchyPage (root page),
// then Copc.loadPointDataView per node; points.node holds each point's node key.
'use strict';
const { Copc } = require('copc');

const DIMENSIONS = ['X', 'Y', 'Z', 'GpsTime', 'Intensity', 'Classification', 'PointSourceId'];

async function main(file) {
  const copc = await Copc.create(file);
  const { nodes, pages } = await Copc.loadHierarchyPage(file, copc.info.rootHierarchyPage);
  const extraNames = copc.eb.map((eb) => eb.name);
  const points = { node: [] };
  for (const name of [...DIMENSIONS, ...extraNames]) points[name] = [];
  const counts = {};
  for (const [key, node] of Object.entries(nodes)) {
    counts[key] = node.pointCount;
    const view = await Copc.loadPointDataView(file, copc, node);
    for (const name of [...DIMENSIONS, ...extraNames]) {
      const get = view.getter(name);
      for (let i = 0; i < view.pointCount; ++i) points[name].push(get(i));
    }
    for (let i = 0; i < view.pointCount; ++i) points.node.push(key);
  }
  const { header, info, wkt, eb } = copc;
  return { header, info, wkt, extraBytes: eb, nodes: counts, pages: Object.keys(pages), points };
}

main(process.argv[2])
  .then((result) => process.stdout.write(JSON.stringify(result)))
  .catch((err) => {
    console.error(err && err.stack ? err.stack : String(err));
    process.exit(1);
  });
