// The REST client: every request carries the token kept in localStorage; every failure is an ApiError whose
// message is one readable line (method, path, status and the service's `detail`).
import { failureMessage } from "./format.js";

export const TOKEN_KEY = "sfmnerf.token";

export class ApiError extends Error {}

function authHeaders() {
  const token = localStorage.getItem(TOKEN_KEY);
  return token ? { Authorization: `Bearer ${token}` } : {};
}

async function describeFailure(response) {
  let body = null;
  try { body = await response.json(); } catch { /* not JSON: the status line says enough */ }
  return failureMessage(response.status, response.statusText, body);
}

export async function api(path, options = {}) {
  let response;
  try {
    response = await fetch(path, { ...options, headers: { ...authHeaders(), ...(options.headers || {}) } });
  } catch (error) {
    throw new ApiError(`cannot reach the service (${error.message})`);
  }
  if (!response.ok) throw new ApiError(`${options.method || "GET"} ${path}: ${await describeFailure(response)}`);
  return response;
}

export const getJson = async (path) => (await api(path)).json();

export const postJson = async (path, body) => (await api(path, {
  method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) })).json();

// An object URL of a response's body (images, videos, downloads need the token, so no plain src= link).
export async function blobUrl(path, options) {
  return URL.createObjectURL(await (await api(path, options)).blob());
}

export async function download(path, filename) {
  const link = Object.assign(document.createElement("a"), { href: await blobUrl(path), download: filename });
  link.click();
  setTimeout(() => URL.revokeObjectURL(link.href), 60_000);
}
