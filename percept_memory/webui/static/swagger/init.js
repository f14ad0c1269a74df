// The API page (/docs): Swagger UI on this app's OpenAPI document, whose URL the page names.
// A static file, as the page's Content-Security-Policy runs no inline script.
"use strict";
const root = document.getElementById("swagger-ui");
SwaggerUIBundle({ url: root.dataset.openapiUrl, domNode: root, deepLinking: true });
