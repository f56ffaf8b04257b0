// Runs lightfield's outputs through real consumers and prints what they see, as JSON.
// Usage: node consumers.mjs <command> <file> [json-args]
//   sh    <json file: {"coefficients": [27 floats], "normals": [[x,y,z], ...]}>  -> SphericalHarmonics3 getAt / getIrradianceAt
//   exr   <file.exr>   -> three's EXRLoader (FloatType): width, height, flipY, colorSpace, data (RGBA rows as stored)
//   gltf  <file.glb>   -> the Khronos glTF validator's report
//   ktx2  <file.ktx2>  -> three's bundled ktx-parse: header fields and level data as floats
import { readFileSync } from 'node:fs';
import * as THREE from 'three';
import { EXRLoader } from 'three/examples/jsm/loaders/EXRLoader.js';
import { read as readKTX2 } from 'three/examples/jsm/libs/ktx-parse.module.js';
import validator from 'gltf-validator';

const [command, file] = process.argv.slice(2);
const bytes = () => new Uint8Array(readFileSync(file));

async function main() {
  if (command === 'sh') {
    const req = JSON.parse(readFileSync(file, 'utf8'));
    const sh = new THREE.SphericalHarmonics3().fromArray(req.coefficients);
    const v = new THREE.Vector3();
    const at = req.normals.map((n) => sh.getAt(new THREE.Vector3(...n), v.clone()).toArray());
    const irradiance = req.normals.map((n) => sh.getIrradianceAt(new THREE.Vector3(...n), v.clone()).toArray());
    return { at, irradiance };
  }
  if (command === 'exr') {
    const loader = new EXRLoader().setDataType(THREE.FloatType);
    const buf = readFileSync(file);
    const tex = loader.parse(buf.buffer.slice(buf.byteOffset, buf.byteOffset + buf.byteLength));
    return { width: tex.width, height: tex.height, flipY: tex.flipY, colorSpace: tex.colorSpace,
             format: tex.format, data: Array.from(tex.data) };
  }
  if (command === 'gltf') {
    return await validator.validateBytes(bytes(), { maxIssues: 100 });
  }
  if (command === 'ktx2') {
    const c = readKTX2(bytes());
    const levels = c.levels.map((l) => {
      const d = l.levelData;
      if (c.typeSize === 4) return Array.from(new Float32Array(d.buffer.slice(d.byteOffset, d.byteOffset + d.byteLength)));
      const u16 = new Uint16Array(d.buffer, d.byteOffset, d.byteLength / 2);
      return Array.from(u16, (h) => THREE.DataUtils.fromHalfFloat(h));
    });
    return { vkFormat: c.vkFormat, typeSize: c.typeSize, pixelWidth: c.pixelWidth, pixelHeight: c.pixelHeight,
             faceCount: c.faceCount, levelCount: c.levels.length, layerCount: c.layerCount,
             dfd: c.dataFormatDescriptor[0], keyValue: c.keyValue, levels };
  }
  throw new Error(`unknown command ${command}`);
}

main().then((out) => process.stdout.write(JSON.stringify(out)), (err) => { console.error(err); process.exit(1); });
