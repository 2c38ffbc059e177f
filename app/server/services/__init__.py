"""What the routes call: sessions, calibration, jobs. No FastAPI in here except UploadFile-like streams."""
