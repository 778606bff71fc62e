"""Loopback services for tests and benches: an S3 server (moto's emulator, ``moto[server]``,
not AWS), a private redis-server's command line and a small generated world.

:func:`start_s3_server` starts the S3 server in a thread of the calling process on a free port of
127.0.0.1; processes the test starts reach it over HTTP at the returned endpoint. Clients
need :data:`TEST_CREDENTIALS` in their environment (moto accepts any).
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import boto3
from moto.server import ThreadedMotoServer

TEST_CREDENTIALS = {
    "AWS_ACCESS_KEY_ID": "testing",
    "AWS_SECRET_ACCESS_KEY": "testing",
    "AWS_DEFAULT_REGION": "us-east-1",
}


def start_s3_server() -> tuple[str, Callable[[], None]]:
    """(endpoint URL ``http://127.0.0.1:<port>``, a function that stops the server)."""
    logging.getLogger("werkzeug").setLevel(logging.WARNING)  # no line per request
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    return f"http://{host}:{port}", server.stop


def client(endpoint_url: str) -> Any:
    """A boto3 S3 client of the test server (test credentials, not the environment's)."""
    return boto3.session.Session(
        aws_access_key_id=TEST_CREDENTIALS["AWS_ACCESS_KEY_ID"],
        aws_secret_access_key=TEST_CREDENTIALS["AWS_SECRET_ACCESS_KEY"],
        region_name=TEST_CREDENTIALS["AWS_DEFAULT_REGION"],
    ).client("s3", endpoint_url=endpoint_url)


def create_bucket(endpoint_url: str) -> str:
    """A new empty bucket with a random name; returns the name."""
    name = f"twindelta-test-{uuid.uuid4().hex[:12]}"
    client(endpoint_url).create_bucket(Bucket=name)
    return name


def object_keys(endpoint_url: str, bucket: str) -> list[str]:
    """Every key in ``bucket``, sorted."""
    pages = client(endpoint_url).get_paginator("list_objects_v2").paginate(Bucket=bucket)
    return sorted(item["Key"] for page in pages for item in page.get("Contents", ()))


def drop_bucket(endpoint_url: str, bucket: str) -> None:
    """Delete ``bucket`` and everything in it (frees the emulator's memory)."""
    s3 = client(endpoint_url)
    for upload in s3.list_multipart_uploads(Bucket=bucket).get("Uploads", ()):
        s3.abort_multipart_upload(Bucket=bucket, Key=upload["Key"], UploadId=upload["UploadId"])
    keys = object_keys(endpoint_url, bucket)
    for start in range(0, len(keys), 1000):
        batch = [{"Key": k} for k in keys[start : start + 1000]]
        s3.delete_objects(Bucket=bucket, Delete={"Objects": batch, "Quiet": True})
    s3.delete_bucket(Bucket=bucket)


def redis_command(binary: str, port: int, folder: Path) -> list[str]:
    """A private, non-persistent redis-server on 127.0.0.1:``port`` working in ``folder``."""
    flags = ["--bind", "127.0.0.1", "--save", "", "--appendonly", "no"]
    return [binary, "--port", str(port), *flags, "--dir", str(folder)]


def generate_world(
    out: Path, scenario: str, seed: int, views: int, size_px: tuple[int, int], focal_px: float
) -> Path:
    """The demo preset's world for ``scenario`` (before/, after/, ground_truth.json) with
    ``views`` photos of ``size_px`` (width, height) per capture, written under ``out``."""
    from workers.pipeline.synth import generate, preset

    options = preset("demo")
    options = replace(
        options,
        path=replace(options.path, n_views=views),
        camera=replace(options.camera, width=size_px[0], height=size_px[1], focal_px=focal_px),
    )
    generate(out, scenario, seed, options)
    return out
