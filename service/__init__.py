"""HTTP service for CREStereo++ stereo disparity: FastAPI app with dynamic CPU batching.

Run: `uvicorn service.app:create_app --factory`; configuration in `service/README.md`.
"""
