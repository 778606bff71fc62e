// The 3D view: snapshot clouds, change clusters coloured by type, library models at their
// poses (previous pose as a translucent ghost), camera frusta; orbit/pan/zoom; picking.
// The environment frame is z-up (docs/contract.md), metres; poses are env_from_object.

import * as THREE from "three";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";
import type { Cloud } from "./ply";
import type { ClusterPoints, ImageInfo, Matrix4 } from "./api";

export const CHANGE_COLOURS: Record<string, string> = {
  added: "#2fbf71",
  removed: "#e5484d",
  moved: "#f5a524",
  swapped: "#a06cd5",
  unidentified: "#9aa5b1",
  unchanged: "#4aa3df",
};
export const CLEAR_COLOUR = 0x14171c;

export type Pick = { kind: "object"; key: string } | { kind: "frustum"; image: string };

export type Layer = "before" | "after" | "clusters" | "models" | "ghosts" | "cameras";

export function matrixOf(rows: Matrix4): THREE.Matrix4 {
  const m = new THREE.Matrix4();
  m.set(
    rows[0][0], rows[0][1], rows[0][2], rows[0][3],
    rows[1][0], rows[1][1], rows[1][2], rows[1][3],
    rows[2][0], rows[2][1], rows[2][2], rows[2][3],
    rows[3][0], rows[3][1], rows[3][2], rows[3][3],
  );
  return m;
}

export class Viewer {
  readonly renderer: THREE.WebGLRenderer;
  readonly scene = new THREE.Scene();
  readonly camera: THREE.PerspectiveCamera;
  readonly controls: OrbitControls;
  readonly layers: Record<Layer, THREE.Group>;
  onPick: (pick: Pick) => void = () => {};
  private raycaster = new THREE.Raycaster();
  private frameRequested = false;
  private resizeObserver: ResizeObserver;
  private selected: THREE.Object3D[] = [];
  private fitted = false;

  constructor(readonly container: HTMLElement) {
    // preserveDrawingBuffer: the canvas can be read back (tests, screenshots) between frames
    this.renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
    this.renderer.setClearColor(CLEAR_COLOUR);
    this.renderer.domElement.dataset.testid = "viewer-canvas";
    this.renderer.domElement.setAttribute("aria-label", "3D view of the environment");
    container.appendChild(this.renderer.domElement);
    this.camera = new THREE.PerspectiveCamera(50, 1, 0.01, 500);
    this.camera.up.set(0, 0, 1); // the environment frame is z-up
    this.camera.position.set(4, -4, 3);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.enableDamping = false;
    this.controls.screenSpacePanning = true;
    this.controls.addEventListener("change", () => this.requestRender());
    this.layers = {
      before: new THREE.Group(),
      after: new THREE.Group(),
      clusters: new THREE.Group(),
      models: new THREE.Group(),
      ghosts: new THREE.Group(),
      cameras: new THREE.Group(),
    };
    for (const g of Object.values(this.layers)) this.scene.add(g);
    this.layers.before.visible = false;
    this.scene.add(new THREE.AmbientLight(0xffffff, 1.6));
    const sun = new THREE.DirectionalLight(0xffffff, 2.0);
    sun.position.set(3, -2, 6);
    this.scene.add(sun);
    const grid = new THREE.GridHelper(10, 20, 0x3a404a, 0x262a31);
    grid.rotation.x = Math.PI / 2; // GridHelper lies in x-z; the floor here is x-y
    this.scene.add(grid);
    this.scene.add(new THREE.AxesHelper(0.5));
    this.raycaster.params.Points = { threshold: 0.02 };
    this.raycaster.params.Line = { threshold: 0.02 };
    this.bindPicking();
    this.resizeObserver = new ResizeObserver(() => this.resize());
    this.resizeObserver.observe(container);
    this.resize();
  }

  dispose(): void {
    this.resizeObserver.disconnect();
    this.controls.dispose();
    this.scene.traverse((o) => {
      const any = o as THREE.Mesh;
      any.geometry?.dispose?.();
      const mats = Array.isArray(any.material) ? any.material : any.material ? [any.material] : [];
      mats.forEach((m) => m.dispose());
    });
    this.renderer.dispose();
    this.renderer.domElement.remove();
  }

  resize(): void {
    const w = Math.max(1, this.container.clientWidth);
    const h = Math.max(1, this.container.clientHeight);
    this.renderer.setSize(w, h, true);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.renderNow();
  }

  requestRender(): void {
    if (this.frameRequested) return;
    this.frameRequested = true;
    requestAnimationFrame(() => {
      this.frameRequested = false;
      this.renderNow();
    });
  }

  renderNow(): void {
    this.renderer.render(this.scene, this.camera);
  }

  /** Resolves after the next frame was drawn (for timing the cloud load). */
  drawn(): Promise<number> {
    this.renderNow();
    return new Promise((resolve) => requestAnimationFrame(() => resolve(performance.now())));
  }

  setVisible(layer: Layer, visible: boolean): void {
    this.layers[layer].visible = visible;
    this.requestRender();
  }

  clear(layer: Layer): void {
    const g = this.layers[layer];
    for (const child of [...g.children]) {
      g.remove(child);
      child.traverse((o) => {
        const m = o as THREE.Mesh;
        m.geometry?.dispose?.();
      });
    }
  }

  setCloud(layer: "before" | "after", cloud: Cloud): void {
    this.clear(layer);
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(cloud.positions, 3));
    if (cloud.colors) geometry.setAttribute("color", new THREE.BufferAttribute(cloud.colors, 3, true));
    geometry.computeBoundingBox();
    geometry.computeBoundingSphere();
    const material = new THREE.PointsMaterial({
      size: 2,
      sizeAttenuation: false,
      vertexColors: !!cloud.colors,
      color: cloud.colors ? 0xffffff : layer === "before" ? 0x8899aa : 0xcfd6df,
      transparent: layer === "before",
      opacity: layer === "before" ? 0.6 : 1,
    });
    const points = new THREE.Points(geometry, material);
    points.name = `${layer}-cloud`;
    points.raycast = () => {}; // the cloud itself is never picked (millions of points)
    this.layers[layer].add(points);
    if (!this.fitted && geometry.boundingBox) {
      this.fitTo(geometry.boundingBox);
      this.fitted = true;
    }
    this.requestRender();
  }

  fitTo(box: THREE.Box3): void {
    const centre = box.getCenter(new THREE.Vector3());
    const size = box.getSize(new THREE.Vector3());
    const radius = Math.max(size.length() / 2, 0.1);
    const distance = radius / Math.sin(THREE.MathUtils.degToRad(this.camera.fov / 2));
    const dir = new THREE.Vector3(0.6, -0.9, 0.7).normalize();
    this.camera.position.copy(centre).addScaledVector(dir, distance * 0.85);
    this.camera.near = Math.max(distance / 1000, 0.005);
    this.camera.far = distance * 20;
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(centre);
    this.controls.update();
  }

  /** Clusters' points coloured by their change's type (or by side without a change). */
  setClusters(clusters: ClusterPoints[], typeOfChange: (changeId: string | null) => string | null): void {
    this.clear("clusters");
    for (const c of clusters) {
      const type = typeOfChange(c.change_id);
      const geometry = new THREE.BufferGeometry();
      geometry.setAttribute("position", new THREE.BufferAttribute(new Float32Array(c.positions), 3));
      // a cluster no change explains (unidentified) is drawn faint, in its side's colour
      const material = new THREE.PointsMaterial({
        size: type ? 4 : 2,
        sizeAttenuation: false,
        color: new THREE.Color(CHANGE_COLOURS[type ?? c.side] ?? "#ffffff"),
        transparent: !type,
        opacity: type ? 1 : 0.35,
      });
      const points = new THREE.Points(geometry, material);
      points.name = `cluster-${c.id}`;
      points.userData = c.change_id ? { pick: { kind: "object", key: `change:${c.change_id}` } } : {};
      this.layers.clusters.add(points);
    }
    this.requestRender();
  }

  /** A model drawn at env_from_object; a ghost is translucent and never picked. */
  addModel(model: THREE.Object3D, envFromObject: Matrix4, key: string, colour: string, ghost = false): THREE.Object3D {
    const holder = new THREE.Group();
    holder.matrixAutoUpdate = false;
    holder.matrix.copy(matrixOf(envFromObject));
    holder.name = ghost ? `ghost:${key}` : key;
    const copy = model.clone(true);
    copy.traverse((o) => {
      const mesh = o as THREE.Mesh;
      if (!mesh.isMesh && !(o as THREE.Points).isPoints) return;
      const base = new THREE.Color(colour);
      if ((o as THREE.Points).isPoints) {
        mesh.material = new THREE.PointsMaterial({ size: 3, sizeAttenuation: false, color: base, transparent: ghost, opacity: ghost ? 0.35 : 1 });
      } else {
        mesh.material = new THREE.MeshStandardMaterial({
          color: base,
          transparent: ghost,
          opacity: ghost ? 0.3 : 0.92,
          depthWrite: !ghost,
          roughness: 0.6,
          metalness: 0.05,
        });
      }
      if (!ghost) mesh.userData = { pick: { kind: "object", key } };
      else mesh.raycast = () => {};
    });
    holder.add(copy);
    (ghost ? this.layers.ghosts : this.layers.models).add(holder);
    this.requestRender();
    return holder;
  }

  /** A marker (small box) for an object whose model is not available. */
  addMarker(envFromObject: Matrix4, key: string, colour: string): void {
    const mesh = new THREE.Mesh(
      new THREE.BoxGeometry(0.08, 0.08, 0.08),
      new THREE.MeshStandardMaterial({ color: new THREE.Color(colour), transparent: true, opacity: 0.8 }),
    );
    mesh.matrixAutoUpdate = false;
    mesh.matrix.copy(matrixOf(envFromObject));
    mesh.userData = { pick: { kind: "object", key } };
    mesh.name = key;
    this.layers.models.add(mesh);
    this.requestRender();
  }

  /** One frustum per registered image: apex at the camera, the image plane at depth_m. */
  setFrusta(images: ImageInfo[], depthM: number): void {
    this.clear("cameras");
    const lineMaterial = new THREE.LineBasicMaterial({ color: 0x9fb3c8 });
    const fillMaterial = new THREE.MeshBasicMaterial({ color: 0x9fb3c8, transparent: true, opacity: 0.12, side: THREE.DoubleSide, depthWrite: false });
    for (const image of images) {
      if (!image.camera) continue;
      const K = image.camera.K;
      const fx = K[0][0], fy = K[1][1], cx = K[0][2], cy = K[1][2];
      const corner = (u: number, v: number) => new THREE.Vector3(((u - cx) / fx) * depthM, ((v - cy) / fy) * depthM, depthM);
      const c = [corner(0, 0), corner(image.width, 0), corner(image.width, image.height), corner(0, image.height)];
      const o = new THREE.Vector3();
      const seg = [o, c[0], o, c[1], o, c[2], o, c[3], c[0], c[1], c[1], c[2], c[2], c[3], c[3], c[0]];
      const holder = new THREE.Group();
      holder.matrixAutoUpdate = false;
      holder.matrix.copy(matrixOf(image.camera.env_from_cam)); // OpenCV camera axes
      holder.name = `frustum:${image.name}`;
      const lines = new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints(seg), lineMaterial);
      lines.raycast = () => {};
      const quad = new THREE.BufferGeometry().setFromPoints([c[0], c[1], c[2], c[0], c[2], c[3]]);
      const fill = new THREE.Mesh(quad, fillMaterial);
      fill.userData = { pick: { kind: "frustum", image: image.name } };
      holder.add(lines, fill);
      this.layers.cameras.add(holder);
    }
    this.requestRender();
  }

  highlight(key: string | null): void {
    for (const o of this.selected) {
      const mat = (o as THREE.Mesh).material as THREE.MeshStandardMaterial;
      if (mat?.emissive) mat.emissive.setHex(0x000000);
    }
    this.selected = [];
    if (!key) return this.requestRender();
    this.layers.models.traverse((o) => {
      const pick = o.userData.pick as Pick | undefined;
      if (pick?.kind === "object" && pick.key === key) {
        const mat = (o as THREE.Mesh).material as THREE.MeshStandardMaterial;
        if (mat?.emissive) {
          mat.emissive.setHex(0x333333);
          this.selected.push(o);
        }
      }
    });
    this.requestRender();
  }

  /** Orbit around the object drawn under ``key`` (its pose's origin), closer by half. */
  focusOn(key: string): void {
    const holder = this.layers.models.children.find((o) => o.name === key);
    if (!holder) return;
    const target = new THREE.Vector3().setFromMatrixPosition(holder.matrix);
    const offset = this.camera.position.clone().sub(this.controls.target).multiplyScalar(0.5);
    if (offset.length() < 0.5) offset.setLength(0.5);
    this.controls.target.copy(target);
    this.camera.position.copy(target).add(offset);
    this.controls.update();
    this.requestRender();
  }

  private bindPicking(): void {
    const canvas = this.renderer.domElement;
    let down: { x: number; y: number } | null = null;
    canvas.addEventListener("pointerdown", (e) => (down = { x: e.clientX, y: e.clientY }));
    canvas.addEventListener("pointerup", (e) => {
      if (!down || Math.hypot(e.clientX - down.x, e.clientY - down.y) > 4) return;
      const pick = this.pickAt(e.clientX, e.clientY);
      if (pick) this.onPick(pick);
    });
  }

  pickAt(clientX: number, clientY: number): Pick | null {
    const r = this.renderer.domElement.getBoundingClientRect();
    const ndc = new THREE.Vector2(((clientX - r.left) / r.width) * 2 - 1, -((clientY - r.top) / r.height) * 2 + 1);
    this.raycaster.setFromCamera(ndc, this.camera);
    const targets = [this.layers.models, this.layers.clusters, this.layers.cameras].filter((g) => g.visible);
    for (const hit of this.raycaster.intersectObjects(targets, true)) {
      const pick = hit.object.userData.pick as Pick | undefined;
      if (pick) return pick;
    }
    return null;
  }
}
