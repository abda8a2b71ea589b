// Entry of the three.js bundle (web/vendor/build-three.sh): the whole `three` namespace plus
// OrbitControls, as one classic script that defines `window.THREE` (file:// pages cannot load
// ES modules from other files).
export * from 'three';
export { OrbitControls } from 'three/addons/controls/OrbitControls.js';
