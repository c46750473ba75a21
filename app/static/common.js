// Shared by the pages: who is acting and REST calls. One name per person: typed in the page header,
// sent as X-Author with every REST call and mirrored into the slam6d-author cookie, which the 3D view's
// websocket carries, so the buttons in the 3D view act under the same name.
export function authorName() {
  return localStorage.getItem("slam6d-author") || "";
}

function storeAuthorCookie(name) {
  document.cookie = `slam6d-author=${encodeURIComponent(name)}; path=/; SameSite=Strict; max-age=31536000`;
}

export function bindAuthorField(input, onChange = () => {}) {
  input.value = authorName();
  storeAuthorCookie(authorName());
  input.addEventListener("change", () => {
    localStorage.setItem("slam6d-author", input.value.trim());
    storeAuthorCookie(input.value.trim());
    onChange(input.value.trim());
  });
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
