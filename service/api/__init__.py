"""The REST API, laid out like the FastAPI full-stack template's ``backend/app/api``.

``deps`` holds the dependencies routes declare (``StoreDep``, ``CurrentTenant``, ...),
``models`` the request and response bodies, ``routes/`` one ``APIRouter`` per resource and
``limits`` the request-body limit; ``service.app.create_app`` assembles them.
"""

__all__: list[str] = []
