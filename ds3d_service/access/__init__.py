"""Who may call the service: API keys (keys), request rates per caller (ratelimit), and the
middleware that applies both and logs each request (rules)."""
