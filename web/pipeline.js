// The pipeline as the server describes it (GET /api/v1/pipeline): stages with their labels, the parameter
// form, the 2D labelers and the run states. Fetched once per page load; the UI declares none of these itself.

import { get } from "./api.js";

let pending = null;

/** The pipeline description (one request per page load; a failed request is retried on the next call). */
export function pipelineInfo() {
  if (!pending) {
    pending = get("/pipeline").catch((err) => {
      pending = null;
      throw err;
    });
  }
  return pending;
}
