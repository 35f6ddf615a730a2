//! Django-level HTML error pages (EvalAI's 404 and 500 templates: both titled as its home page).

/// The page Django renders for an unresolved URL.
pub const NOT_FOUND: &str = "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>EvalAI- Home Page</title>\n</head>\n<body>\n<div class=\"error-page\">\n<h1>404</h1>\n<h3>Page not found</h3>\n<p>The page you are looking for does not exist or has been moved.</p>\n<a href=\"/\">Go back to home</a>\n</div>\n</body>\n</html>\n";

/// The page Django renders for an unhandled exception.
pub const SERVER_ERROR: &str = "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>EvalAI- Home Page</title>\n</head>\n<body>\n<div class=\"error-page\">\n<h1>500</h1>\n<h3>Server error</h3>\n<p>Something went wrong. We have been notified and will fix it soon.</p>\n<a href=\"/\">Go back to home</a>\n</div>\n</body>\n</html>\n";

/// Content type of both pages.
pub const CONTENT_TYPE: &str = "text/html; charset=utf-8";
