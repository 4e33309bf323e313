"""Artifact storage in an S3-compatible bucket (AWS S3, MinIO...), through boto3.

Selected by ``CMC_STORAGE=s3://bucket/prefix``: every key of :mod:`service.storage` becomes the
object ``prefix/key``. Credentials come from boto3's usual chain (``AWS_ACCESS_KEY_ID`` /
``AWS_SECRET_ACCESS_KEY``, a profile, an instance role); ``CMC_S3_ENDPOINT_URL`` points at a
server other than AWS (path-style addressing then). Files from ``CMC_S3_MULTIPART_BYTES`` up are
uploaded in parts by boto3's managed transfer; S3 shows an object only once its last part is in,
so a writer killed mid-upload leaves the previous object as it was (the parts of an abandoned
upload stay billed until a lifecycle rule aborts them). Clients download stored files straight
from the bucket through presigned GET URLs (:meth:`S3Storage.locate`), signed for
``CMC_S3_PUBLIC_ENDPOINT_URL`` when the API reaches the bucket at another address than clients.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import boto3
from boto3.s3.transfer import TransferConfig
from botocore.config import Config
from botocore.exceptions import BotoCoreError, ClientError

from service.settings import Settings
from service.storage.base import Storage, StorageError, check_key

_MISSING = {"404", "NoSuchKey", "NotFound"}


def _missing(e: ClientError) -> bool:
    return str(e.response.get("Error", {}).get("Code")) in _MISSING


class S3Storage(Storage):
    """Artifacts as objects ``prefix/key`` in ``bucket``; local working copies under ``work_dir``."""

    def __init__(
        self,
        bucket: str,
        prefix: str,
        work_dir: str | Path,
        endpoint_url: str = "",
        public_endpoint_url: str = "",
        region: str = "",
        url_seconds: int = 3600,
        multipart_bytes: int = 16 << 20,
    ):
        self.bucket, self.prefix = bucket, prefix.strip("/")
        self.work_dir = Path(work_dir)
        self.endpoint_url, self.url_seconds = endpoint_url, url_seconds
        self.transfer = TransferConfig(multipart_threshold=multipart_bytes, multipart_chunksize=multipart_bytes)
        config = Config(
            signature_version="s3v4",
            s3={"addressing_style": "path" if endpoint_url else "auto"},
            retries={"max_attempts": 3, "mode": "standard"},
            connect_timeout=5,
            read_timeout=60,
        )
        self.client = boto3.client("s3", endpoint_url=endpoint_url or None, region_name=region or None, config=config)
        public = public_endpoint_url or endpoint_url  # presigning is local: no request goes there
        self._signer = boto3.client("s3", endpoint_url=public or None, region_name=region or None, config=config)

    @classmethod
    def from_settings(cls, s: Settings) -> S3Storage:
        bucket, _, prefix = s.storage.removeprefix("s3://").partition("/")
        return cls(
            bucket,
            prefix,
            s.work_dir,
            s.s3_endpoint_url,
            s.s3_public_endpoint_url,
            s.s3_region,
            s.s3_url_seconds,
            s.s3_multipart_bytes,
        )

    def __repr__(self) -> str:
        return f"S3Storage(s3://{self.bucket}/{self.prefix} at {self.endpoint_url or 'AWS'})"

    def _obj(self, key: str) -> str:
        check_key(key)
        return f"{self.prefix}/{key}" if self.prefix else key

    def _key(self, obj: str) -> str:
        return obj[len(self.prefix) + 1 :] if self.prefix else obj

    def write_bytes(self, key: str, data: bytes) -> None:
        self.client.put_object(Bucket=self.bucket, Key=self._obj(key), Body=data)

    def read_bytes(self, key: str) -> bytes:
        try:
            return self.client.get_object(Bucket=self.bucket, Key=self._obj(key))["Body"].read()
        except ClientError as e:
            if _missing(e):
                raise StorageError(f"no artifact {key}") from None
            raise

    def exists(self, key: str) -> bool:
        try:
            self.client.head_object(Bucket=self.bucket, Key=self._obj(key))
        except ClientError as e:
            if _missing(e):
                return False
            raise
        except StorageError:
            return False
        return True

    def list(self, prefix: str) -> list[str]:
        pages = self.client.get_paginator("list_objects_v2").paginate(
            Bucket=self.bucket, Prefix=self._obj(prefix) + "/"
        )
        return sorted(self._key(o["Key"]) for page in pages for o in page.get("Contents", []))

    def delete(self, key: str) -> None:
        self.client.delete_object(Bucket=self.bucket, Key=self._obj(key))

    def _delete_many(self, keys: list[str]) -> None:
        for i in range(0, len(keys), 1000):  # the most one request may name
            batch = [{"Key": self._obj(k)} for k in keys[i : i + 1000]]
            out = self.client.delete_objects(Bucket=self.bucket, Delete={"Objects": batch, "Quiet": True})
            if out.get("Errors"):
                raise StorageError(f"could not delete {out['Errors'][0]}")

    def delete_scene(self, scene_id: str) -> None:
        self._delete_many(self.list(scene_id))

    def publish(self, key: str, src: Path, manifest: str | None = None) -> None:
        if not src.is_dir():
            self.client.upload_file(str(src), self.bucket, self._obj(key), Config=self.transfer)
            return
        new = sorted(p.relative_to(src).as_posix() for p in src.rglob("*") if p.is_file())
        old = set(self.list(key))
        if manifest is not None and f"{key}/{manifest}" in old:
            self.delete(f"{key}/{manifest}")  # first: no reader takes the old manifest for the new files
        for name in sorted(new, key=lambda n: n == manifest):  # the manifest last
            self.client.upload_file(str(src / name), self.bucket, self._obj(f"{key}/{name}"), Config=self.transfer)
        self._delete_many(sorted(old - {f"{key}/{n}" for n in new}))

    @contextmanager
    def reading(self, key: str) -> Iterator[Path]:
        with self.scratch() as tmp:
            dst = tmp / key.rsplit("/", 1)[-1]
            if self.exists(key):
                self.client.download_file(self.bucket, self._obj(key), str(dst), Config=self.transfer)
            else:
                for k in self.list(key):
                    target = dst / k[len(key) + 1 :]
                    target.parent.mkdir(parents=True, exist_ok=True)
                    self.client.download_file(self.bucket, self._obj(k), str(target), Config=self.transfer)
            yield dst

    def locate(self, key: str, media_type: str, filename: str | None = None) -> str:
        params = {"Bucket": self.bucket, "Key": self._obj(key), "ResponseContentType": media_type}
        if filename is not None:
            params["ResponseContentDisposition"] = f'attachment; filename="{filename}"'
        return self._signer.generate_presigned_url("get_object", Params=params, ExpiresIn=self.url_seconds)

    def check(self) -> None:
        probe = f"{self.prefix}/.probe" if self.prefix else ".probe"
        try:
            self.client.put_object(Bucket=self.bucket, Key=probe, Body=b"ok")
            self.client.delete_object(Bucket=self.bucket, Key=probe)
        except (BotoCoreError, ClientError) as e:
            raise StorageError(f"cannot write to {self!r}: {e}") from None
