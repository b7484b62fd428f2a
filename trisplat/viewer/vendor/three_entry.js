// The parts of three.js the viewer uses; esbuild bundles and tree-shakes them into static/three.bundle.min.js.
export {
  AmbientLight, BufferAttribute, BufferGeometry, Color, ColorManagement, DirectionalLight, DoubleSide,
  Float32BufferAttribute, Group, LineBasicMaterial, LineSegments, LinearSRGBColorSpace, Matrix4, Mesh,
  MeshBasicMaterial, MeshLambertMaterial, NoToneMapping, PerspectiveCamera, Quaternion, Scene, Spherical,
  SRGBColorSpace, Vector3, WebGLRenderer,
} from 'three';
export { OrbitControls } from 'three/addons/controls/OrbitControls.js';
// mesh.glb is loaded as any engine loads it (KHR_materials_unlit -> MeshBasicMaterial, sRGB base colour texture)
export { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
