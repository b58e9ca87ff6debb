// The pipeline as the server describes it (GET /api/v1/pipeline): stages with their labels, the parameter
// form, the 2D labelers and the run states. Fetched once per page load; the UI declares none of these itself.

import { get } from "./api.js";

let info = null;

/** The pipeline description, kept once a request succeeds. Only answers are kept, never a request in
 * flight: one sent before the user gave the access token fails, and a page rendered after the token must
 * not wait on it. */
export async function pipelineInfo() {
  if (info === null) info = await get("/pipeline");
  return info;
}
