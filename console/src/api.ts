// The public twindelta API as the console uses it: Bearer key from sessionStorage, JSON
// bodies, the API's {"error", "detail"} errors turned into ApiError.

const KEY_STORE = "twindelta.apiKey";

export function storedKey(): string | null {
  return sessionStorage.getItem(KEY_STORE);
}

export function storeKey(key: string | null): void {
  if (key) sessionStorage.setItem(KEY_STORE, key);
  else sessionStorage.removeItem(KEY_STORE);
}

export class ApiError extends Error {
  constructor(
    readonly status: number,
    readonly code: string,
    readonly detail: string,
    readonly path: string,
  ) {
    super(`${code}: ${detail}`);
  }
  get unauthorised(): boolean {
    return this.status === 401;
  }
}

/** Listeners told when any call answers 401 (the key was revoked or is wrong). */
const unauthorisedListeners: Array<(e: ApiError) => void> = [];
export function onUnauthorised(fn: (e: ApiError) => void): void {
  unauthorisedListeners.push(fn);
}

export function authHeaders(key = storedKey()): Record<string, string> {
  return key ? { Authorization: `Bearer ${key}` } : {};
}

async function errorOf(res: Response, path: string): Promise<ApiError> {
  let code = `HTTP ${res.status}`;
  let detail = res.statusText || "request failed";
  try {
    const body = await res.json();
    const err = body?.error;
    if (typeof err === "string") {
      code = err;
      detail = body.detail ?? detail;
    } else if (err && typeof err === "object") {
      code = err.code ?? err.error ?? code;
      detail = err.detail ?? err.message ?? detail;
    } else if (body?.detail) {
      detail = typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail);
    }
  } catch {
    /* not JSON */
  }
  const e = new ApiError(res.status, code, detail, path);
  if (e.unauthorised) unauthorisedListeners.forEach((fn) => fn(e));
  return e;
}

export async function request(
  path: string,
  init: RequestInit = {},
  key: string | null = storedKey(),
): Promise<Response> {
  const headers = new Headers(init.headers);
  for (const [k, v] of Object.entries(authHeaders(key))) headers.set(k, v);
  const res = await fetch(path, { ...init, headers });
  if (!res.ok) throw await errorOf(res, path);
  return res;
}

export async function getJson<T>(path: string, key?: string | null): Promise<T> {
  const res = await request(path, {}, key === undefined ? storedKey() : key);
  return (await res.json()) as T;
}

export async function postJson<T>(path: string, body: unknown): Promise<T> {
  const res = await request(path, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(body),
  });
  return (await res.json()) as T;
}

// ---- shapes (the subset the console reads) ----

export type Matrix4 = number[][]; // 4x4 row-major, metres

export interface KeyInfo {
  id: string;
  name: string;
  scopes: string[];
  environment_ids: string[] | null;
}

export interface SnapshotBrief {
  id: string;
  seq: number;
  state: string;
  created_at: string;
}

export interface Environment {
  id: string;
  name: string;
  classes: string[];
  created_at: string;
  twin: { seq: number; snapshot: string | null; status: string; waiting_for: string | null; comparison: string | null };
  twin_object_count?: number;
  last_snapshot?: SnapshotBrief | null;
}

export interface Job {
  id: string;
  kind: string;
  state: string;
  stage: string | null;
  progress: number;
  error: { code: string; detail: string | null } | null;
  cancel_requested: boolean;
  created_at: string;
  finished_at: string | null;
}

export interface Snapshot {
  id: string;
  environment: string;
  seq: number;
  state: string;
  source: string;
  created_at: string;
  reconstructed_at: string | null;
  job: string | null;
  comparison: string | null;
  n_images: number;
  n_detections: number;
  has_cameras: boolean;
  images_deleted_at: string | null;
  quality: Record<string, unknown>;
  twin_update: string | null;
}

export interface Instance {
  instance_id: string;
  external_id: string | null;
  object: string;
  object_id: string | null;
  pose: Matrix4 | null;
  pose_quality: Record<string, unknown> | null;
  since_snapshot: string | null;
  created_snapshot: string | null;
  created_at: string;
  [extra: string]: unknown;
}

export interface TwinState {
  environment: string;
  objects: Instance[];
  at_snapshot: string | null;
}

export interface Change {
  id: string;
  type: "added" | "removed" | "moved" | "swapped" | string;
  object: string | null;
  instance_id: string | null;
  external_id: string | null;
  pose: Matrix4 | null;
  previous_pose: Matrix4 | null;
  replaced_object: string | null;
  replaced_instance_id: string | null;
  replaced_external_id: string | null;
  identification: Record<string, number> | null;
  cluster: { side: string; n_points: number; centroid: number[]; bbox_min?: number[]; bbox_max?: number[] } | null;
  pose_quality: Record<string, unknown> | null;
  centroid_env: number[] | null;
}

export interface Comparison {
  id: string;
  before: string;
  after: string;
  job: string;
  state: string;
  automatic: boolean;
  applied_to_twin: boolean;
  created_at: string;
  completed_at: string | null;
  changes: Change[];
  clusters: Array<{ id: number; side: string; n_points: number; metrics: Record<string, number> }>;
  distances: Record<string, { mean: number; std: number; threshold: number }>;
  options?: Record<string, unknown>;
}

export interface ClusterPoints {
  id: number;
  side: "added" | "removed";
  change_id: string | null;
  n_points: number;
  positions: number[];
}

export interface Detection {
  class_name: string;
  class_id: number;
  box_px: [number, number, number, number];
  confidence: number | null;
}

export interface ImageInfo {
  name: string;
  width: number;
  height: number;
  url: string;
  registered: boolean;
  camera: { K: number[][]; env_from_cam: Matrix4 } | null;
  detections: Detection[];
}

export interface ChangeView {
  image: string;
  outline_px: number[][];
  box_px: number[] | null;
  detection_box_px: number[] | null;
  iou: number | null;
  counted: boolean;
}

export interface LibraryObject {
  id: string;
  name: string;
  state: string;
}

export interface History {
  instance_id: string;
  object: string;
  external_id: string | null;
  poses: Array<{ snapshot: string | null; comparison: string | null; change_type: string; pose: Matrix4 | null; at: string }>;
}

export function canUpload(key: KeyInfo | null): boolean {
  return !!key && (key.scopes.includes("capture") || key.scopes.includes("admin"));
}

export function canCancel(key: KeyInfo | null): boolean {
  return canUpload(key);
}

export function canRerun(key: KeyInfo | null): boolean {
  return !!key && key.scopes.includes("admin");
}

export const FINAL_JOB_STATES = new Set(["succeeded", "failed", "cancelled"]);
