// Shared by the pages: who is acting (sent as X-Author so the journal records it) and REST calls.
export function authorName() {
  return localStorage.getItem("slam6d-author") || "";
}

export function bindAuthorField(input) {
  input.value = authorName();
  input.addEventListener("change", () => localStorage.setItem("slam6d-author", input.value.trim()));
}

export async function api(path, options = {}) {
  const headers = { ...(options.headers || {}) };
  if (authorName()) headers["X-Author"] = authorName();
  const response = await fetch(path, { ...options, headers });
  const text = await response.text();
  let body = text;
  try { body = JSON.parse(text); } catch { /* plain text */ }
  if (!response.ok) {
    const detail = body && body.detail ? body.detail : text;
    throw new Error(typeof detail === "string" ? detail : JSON.stringify(detail));
  }
  return body;
}
