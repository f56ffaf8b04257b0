// Runs lightfield's outputs through real consumers and prints what they see, as JSON.
// Usage: node consumers.mjs <command> <file> [json-args]
//   sh    <json file: {"coefficients": [27 floats], "normals": [[x,y,z], ...]}>  -> SphericalHarmonics3 getAt / getIrradianceAt
//   exr   <file.exr>   -> three's EXRLoader (FloatType): width, height, flipY, colorSpace, data (RGBA rows as stored)
//   gltf  <file.glb>   -> the Khronos glTF validator's report
//   ktx2  <file.ktx2>  -> three's bundled ktx-parse: header fields and level data as floats
//   babylon <json file: {"glb": path, "faces": path of float32 [6, S, S, 3], "size": S, "normals": [[x,y,z], ...]}>
//         -> Babylon.js's own diffuse IBL: the polynomial its glTF loader (@babylonjs/loaders, in a
//            NullEngine, right-handed scene) builds from the .glb's EXT_lights_image_based light, and
//            the one CubeMapToSphericalPolynomialTools projects from the faces, both evaluated with
//            Babylon's shader formula (harmonicsFunctions: computeEnvironmentIrradiance, SH path, x
//            texture level as pbrBlockReflection does); the KHR_lights_punctual light it creates.
import { readFileSync } from 'node:fs';
import * as THREE from 'three';
import { EXRLoader } from 'three/examples/jsm/loaders/EXRLoader.js';
import { read as readKTX2 } from 'three/examples/jsm/libs/ktx-parse.module.js';
import validator from 'gltf-validator';
import { NullEngine } from '@babylonjs/core/Engines/nullEngine.js';
import { Scene } from '@babylonjs/core/scene.js';
import { LoadAssetContainerAsync } from '@babylonjs/core/Loading/sceneLoader.js';
import { RawCubeTexture } from '@babylonjs/core/Materials/Textures/rawCubeTexture.js';
import { InternalTexture, InternalTextureSource } from '@babylonjs/core/Materials/Textures/internalTexture.js';
import { CubeMapToSphericalPolynomialTools } from '@babylonjs/core/Misc/HighDynamicRange/cubemapToSphericalPolynomial.js';
import '@babylonjs/loaders/glTF/2.0/index.js';

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
  if (command === 'babylon') {
    return await babylon(JSON.parse(readFileSync(file, 'utf8')));
  }
  throw new Error(`unknown command ${command}`);
}

// Babylon's shader (Shaders/ShadersInclude/harmonicsFunctions, SPHERICAL_HARMONICS branch) on the
// uniforms materialHelper binds (polynomial.preScaledHarmonics), times the texture level
// (pbrBlockReflection: environmentIrradiance *= vReflectionColor * vReflectionInfos.x).
function shaderIrradiance(polynomial, level, n) {
  const h = polynomial.preScaledHarmonics;
  const [x, y, z] = n;
  const terms = [[h.l00, 1], [h.l1_1, y], [h.l10, z], [h.l11, x], [h.l2_2, y * x], [h.l2_1, y * z],
                 [h.l20, 3 * z * z - 1], [h.l21, z * x], [h.l22, x * x - y * y]];
  const out = [0, 0, 0];
  for (const [v, w] of terms) { out[0] += v.x * w; out[1] += v.y * w; out[2] += v.z * w; }
  return out.map((c) => c * level);
}

async function babylon(req) {
  const engine = new NullEngine();
  // No GPU in Node: the cube texture's storage and the upload of the RGBD images are the only
  // things stubbed; the loader's own code (parsing, SH -> polynomial, lights) runs as in a browser.
  engine.createRawCubeTexture = function (data, size) {
    const t = new InternalTexture(this, InternalTextureSource.CubeRaw);
    t.isCube = true; t.width = t.height = t.baseWidth = t.baseHeight = size;
    return t;
  };
  RawCubeTexture.prototype.updateRGBDAsync = async function (data, polynomial) { this.sphericalPolynomial = polynomial; };
  const scene = new Scene(engine);
  scene.useRightHandedSystem = true;  // glTF's frame; a left-handed scene mirrors z (Babylon's default)
  const container = await LoadAssetContainerAsync(new Uint8Array(readFileSync(req.glb)), scene, { pluginExtension: '.glb' });
  container.addAllToScene();
  const env = scene.environmentTexture;
  const out = { environment: env ? env.name : null, level: env ? env.level : null };
  if (env) out.glb = req.normals.map((n) => shaderIrradiance(env.sphericalPolynomial, env.level, n));
  if (req.faces) {
    const f = new Float32Array(new Uint8Array(readFileSync(req.faces)).buffer);
    const n = req.size * req.size * 3;
    const face = (i) => f.subarray(i * n, (i + 1) * n);
    const cube = { size: req.size, right: face(0), left: face(1), up: face(2), down: face(3), front: face(4), back: face(5),
                   format: 4 /* RGB */, type: 1 /* float */, gammaSpace: false };
    const polynomial = CubeMapToSphericalPolynomialTools.ConvertCubeMapToSphericalPolynomial(cube);
    out.cube = req.normals.map((m) => shaderIrradiance(polynomial, 1.0, m));
  }
  out.lights = scene.lights.map((light) => {
    light.computeTransformedInformation();
    const d = light.transformedDirection || light.direction;
    return { name: light.name, type: light.getClassName(), intensity: light.intensity,
             diffuse: [light.diffuse.r, light.diffuse.g, light.diffuse.b], travels: [d.x, d.y, d.z] };
  });
  scene.dispose();
  engine.dispose();
  return out;
}

// The answer is the last line of stdout (libraries may print banners before it: Babylon's NullEngine does).
main().then((out) => process.stdout.write('\n' + JSON.stringify(out) + '\n'), (err) => { console.error(err); process.exit(1); });
