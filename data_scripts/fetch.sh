# Sourced by the download scripts: fetch URL FILE downloads URL to FILE.
# The bytes go to FILE.part first, and a run that was cut (network, Ctrl-C) leaves them there: the next
# run resumes from them (curl -C -) instead of starting the archive over.  A server without byte ranges
# (curl's exit 33) gets the whole archive again, once; a range it refuses as past the end (HTTP 416: the
# part is whole already, or longer than the archive) hands the part on, and the caller's archive test
# decides.  Any other failure keeps the part for the next run and returns curl's status.
fetch() {
  local url="$1" file="$2" status=0 code=""
  code="$(curl -fL --retry 3 -C - -w '%{http_code}' -o "$file.part" "$url")" || status=$?
  if [ "$status" -eq 33 ]; then
    echo "could not resume $file.part from $url (the server sends no byte ranges): downloading it again" >&2
    rm -f "$file.part"
    status=0
    curl -fL --retry 3 -o "$file.part" "$url" || status=$?
  elif [ "$status" -eq 22 ] && [ "$code" = 416 ]; then
    status=0  # nothing left to fetch
  fi
  [ "$status" -eq 0 ] || return "$status"
  mv "$file.part" "$file"
}
