# Sourced by the download scripts: fetch URL FILE downloads URL to FILE.
# The bytes go to FILE.part first, and a run that was cut (network, Ctrl-C) leaves them there: the next
# run resumes from them (curl -C -) instead of starting the archive over.  Where that cannot work (a
# server without byte ranges, curl's exit 33; a refused range, exit 22, as for a FILE.part that is
# already whole) the part is dropped and the download starts over once.  Returns curl's status.
fetch() {
  local url="$1" file="$2" status=0
  curl -fL --retry 3 -C - -o "$file.part" "$url" || status=$?
  if [ "$status" -eq 33 ] || { [ "$status" -eq 22 ] && [ -s "$file.part" ]; }; then
    echo "could not resume $file.part from $url (curl exit $status): downloading it again" >&2
    rm -f "$file.part"
    status=0
    curl -fL --retry 3 -o "$file.part" "$url" || status=$?
  fi
  [ "$status" -eq 0 ] || return "$status"
  mv "$file.part" "$file"
}
