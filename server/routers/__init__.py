"""The HTTP and WebSocket routes, one APIRouter per resource; server/app.py includes them."""
